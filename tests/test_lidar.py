"""The LIDAR (Kim et al.'s 36 rays, 50 m) returns the analytic distance to known footprints, and the ISS injury
model follows Sobhani's Eq. 11 and Table 1. Real env for the scan, camera off."""

from __future__ import annotations

import math

import numpy as np
import pytest

from envs import UrbanCollisionEnv
from envs.actors import PEDESTRIAN_RADIUS
from envs.injury import SOBHANI_ALPHA, damaged_side, injury_severity_score
from envs.lidar import N_RAYS, RANGE_M, LidarHistory, cast, ray_directions, scan


def test_rays_hit_a_rotated_box_and_a_circle_at_the_analytic_distance():
    dirs = ray_directions(0.0, 4)  # +x, +y, -x, -y
    # a box 10 m ahead, rotated by 90°: its half-width (1 m) now lies along x
    box = np.array([[10.0, 0.0, 0.0, 1.0, 2.0, 1.0]])
    circle = np.array([[0.0, -7.0, 0.5]])
    d = cast(np.zeros(2), dirs, box, circle)
    assert d == pytest.approx([9.0, RANGE_M, RANGE_M, 6.5])
    # a ray at 30° passing 0.5 m from the centre of a 1 m circle 9 m out: it enters sqrt(1 - 0.25) m early
    d30, normal = np.array([math.cos(math.pi / 6), math.sin(math.pi / 6)]), np.array([-0.5, math.sqrt(3) / 2])
    c = np.array([[*(9.0 * d30 + 0.5 * normal), 1.0]])
    assert cast(np.zeros(2), d30[None], np.zeros((0, 6)), c)[0] == pytest.approx(9.0 - math.sqrt(0.75))
    assert cast(np.zeros(2), dirs, np.array([[0.0, 0.0, 1.0, 0.0, 1.0, 1.0]]), np.zeros((0, 3))) == pytest.approx(0)


def test_scan_of_the_env_sees_a_pedestrian_ahead_at_its_distance():
    env = UrbanCollisionEnv(camera=False, family="ncap")
    from envs.ncap import NcapSpec

    env.reset(options={"scenario": NcapSpec("CPNA-25", 40.0)})
    # put the test's pedestrian straight ahead of the ego's centre, 20 m away
    env.actors.ped_xy[0] = (env.ego.x + 20.0, env.ego.y)
    d = scan(env)
    assert d.shape == (N_RAYS,) and d.dtype == np.float32
    assert d[0] == pytest.approx(20.0 - PEDESTRIAN_RADIUS, abs=1e-5)
    view = LidarHistory()
    first = view(env)
    view.note_action([0.5, -1.0])
    second = view(env)
    assert first.shape == (4 * N_RAYS + 2,) and np.array_equal(first[:N_RAYS], first[3 * N_RAYS : 4 * N_RAYS])
    assert second[-2:] == pytest.approx([0.5, -1.0]) and first[0] == pytest.approx(d[0] / RANGE_M)
    env.close()


@pytest.mark.parametrize("side, alpha", [("near", 2.698), ("far", 2.038), ("rear", 1.991)])
def test_iss_follows_sobhani_table_1(side, alpha):
    assert SOBHANI_ALPHA[side] == alpha
    assert injury_severity_score(0.0, side) == pytest.approx(math.exp(alpha))  # ΔV -> 0: e^alpha
    dv_ms = 10.0  # 36 km/h: 2.011e-7 * 0.5 * 1500 * 36^2 = 0.19546
    assert injury_severity_score(dv_ms, side) == pytest.approx(math.exp(2.011e-7 * 750 * 36.0**2 + alpha))
    assert injury_severity_score(dv_ms, side, units="ms") == pytest.approx(math.exp(2.011e-7 * 750 * 100.0 + alpha))
    with pytest.raises(ValueError, match="side"):
        injury_severity_score(1.0, "roof")


def test_damaged_side_from_the_contact_point():
    assert damaged_side(2.25, 0.1, 2.25, 0.9) == "front"
    assert damaged_side(-2.2, -0.3, 2.25, 0.9) == "rear"
    assert damaged_side(0.5, 0.9, 2.25, 0.9) == "near"
    assert damaged_side(-1.0, -0.9, 2.25, 0.9) == "far"
