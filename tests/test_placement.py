"""Where a scenario puts everyone (``envs/actors.py``), checked against what the module and docs/design.md §3
promise, over generated scenarios and seeds: the hazards meet the ego's front bumper exactly at the TTC, the
crossing pedestrian starts on a sidewalk and stops on the far one, and other traffic is where it can never be
rear-ended by an ego that brakes."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from envs import ScenarioSpec
from envs.actors import CAR_POOL, CROSSING_ANGLE_DEG, PEDESTRIAN_POOL, PEDESTRIAN_RADIUS, Actors, build_actors
from envs.scene import EGO_LANE_Y, ONCOMING_LANE_Y, SCENE_X, SIDEWALK_OUTER

PROPERTY = settings(max_examples=80, deadline=None, derandomize=True, database=None)
EGO_X0, EGO_FRONT, CAR_LENGTH, CAR_WIDTH = 0.0, 2.25, 4.5, 1.9

scenarios = st.builds(
    ScenarioSpec,
    seed=st.integers(0, 2**31 - 1),
    ttc=st.floats(0.25, 3.0),
    ego_speed=st.floats(5.0, 35.0),
    pedestrian_speed=st.floats(0.5, 3.0),
    n_cars=st.integers(0, 10),
    n_pedestrians=st.integers(0, 10),
    p_pedestrian=st.sampled_from([0.0, 1.0]),
    p_car=st.sampled_from([0.0, 1.0]),
    hazard_car_speed=st.floats(2.0, 15.0),
)


def place(spec: ScenarioSpec, draw: int) -> tuple[Actors, float]:
    return build_actors(spec, np.random.default_rng(draw), EGO_X0, EGO_FRONT, CAR_LENGTH, CAR_WIDTH)


@PROPERTY
@given(scenarios, st.integers(0, 2**32 - 1))
def test_hazards_meet_the_front_bumper_at_the_ttc(spec, draw):
    actors, junction_x = place(spec, draw)
    bumper = EGO_X0 + EGO_FRONT + spec.ego_speed * spec.ttc
    assert actors.collision_point == (None if spec.hazard == "none" else (bumper, EGO_LANE_Y))
    assert list(actors.car_hazard) == [spec.car_hazard] + [False] * (CAR_POOL - 1)
    assert list(actors.ped_hazard) == [spec.pedestrian_hazard] + [False] * (PEDESTRIAN_POOL - 1)
    if spec.car_hazard:
        xy, vel, heading = actors.car_xy[0], actors.car_vel[0], actors.car_heading[0]
        # out of the side street at its own speed, its centre on the ego's path at the TTC, heading where it drives
        assert junction_x == bumper + CAR_WIDTH / 2 and xy[0] == junction_x
        assert vel[0] == 0.0 and math.isclose(abs(vel[1]), spec.hazard_car_speed)
        assert math.isclose(xy[1] + vel[1] * spec.ttc, EGO_LANE_Y, abs_tol=1e-9)
        assert math.isclose(math.cos(heading), 0.0, abs_tol=1e-12) and math.sin(heading) == np.sign(vel[1])
    else:
        assert 30.0 <= junction_x <= 150.0  # a junction somewhere ahead, with no car coming out of it
    if spec.pedestrian_hazard:
        xy, vel, stop = actors.ped_xy[0], actors.ped_vel[0], actors.ped_stop_y[0]
        at_ttc = xy + vel * spec.ttc
        # just ahead of the bumper at the TTC, somewhere across its width
        assert math.isclose(at_ttc[0], bumper + PEDESTRIAN_RADIUS, abs_tol=1e-9)
        assert abs(at_ttc[1] - EGO_LANE_Y) <= 0.5 + 1e-9
        assert math.isclose(float(np.hypot(*vel)), spec.pedestrian_speed)
        # crossing within 30 degrees of square to the road
        assert abs(vel[0]) <= spec.pedestrian_speed * math.sin(math.radians(CROSSING_ANGLE_DEG)) + 1e-9
        # from a sidewalk: the near one only where the walk fits on it; to the far sidewalk of where it came from
        assert xy[1] >= -(SIDEWALK_OUTER - 0.2) - 1e-9
        towards = np.sign(vel[1])
        assert stop == towards * (SIDEWALK_OUTER - 1.0)
    else:
        assert np.isnan(actors.ped_stop_y[0])


@PROPERTY
@given(scenarios, st.integers(0, 2**32 - 1))
def test_other_traffic_is_where_braking_can_never_be_hit_from_behind(spec, draw):
    actors, _ = place(spec, draw)
    bumper = EGO_X0 + EGO_FRONT + spec.ego_speed * spec.ttc
    first_car, first_ped = int(spec.car_hazard), int(spec.pedestrian_hazard)
    cars = range(first_car, first_car + spec.n_cars)
    peds = range(first_ped, first_ped + spec.n_pedestrians)
    for name in ("car_active", "car_hazard", "ped_active", "ped_hazard"):  # boolean masks, combined with & and ~
        assert getattr(actors, name).dtype == bool, name
    assert list(np.flatnonzero(actors.car_active)) == list(range(first_car + spec.n_cars))
    assert list(np.flatnonzero(actors.ped_active)) == list(range(first_ped + spec.n_pedestrians))
    same_lane = []
    for i in cars:
        (x, y), (vx, vy), heading = actors.car_xy[i], actors.car_vel[i], actors.car_heading[i]
        assert vy == 0.0
        if y == EGO_LANE_Y:  # ahead of the collision point, never slower than the ego, facing the way it drives
            assert bumper + 15.0 <= x and spec.ego_speed <= vx <= 1.2 * spec.ego_speed and heading == 0.0
            same_lane.append(x)
        else:
            assert y == ONCOMING_LANE_Y and -14.0 <= vx <= -6.0 and heading == math.pi
            assert EGO_X0 - 20.0 <= x
    assert bumper + 15.0 + 20.0 >= (same_lane[0] if same_lane else bumper + 15.0)
    # one behind the other, with a gap of at least 8 m
    assert all(b - a >= CAR_LENGTH + 8.0 - 1e-9 for a, b in zip(same_lane, same_lane[1:]))
    for i in peds:  # strolling along a sidewalk
        (x, y), (vx, vy) = actors.ped_xy[i], actors.ped_vel[i]
        assert 4.3 <= abs(y) <= 6.0 and vy == 0.0 and 0.8 <= abs(vx) <= 1.8
        assert EGO_X0 - 10.0 <= x <= min(SCENE_X[1], EGO_X0 + 150.0)
        assert np.isnan(actors.ped_stop_y[i])


def test_both_sides_and_every_kind_of_traffic_occur():
    """The draws that the properties above only bound: over seeded scenarios, hazard cars come from both sides,
    pedestrians start from both sidewalks where they can, and both lanes get traffic."""
    sides, ped_sides, lanes = set(), set(), set()
    for draw in range(60):
        spec = ScenarioSpec(seed=draw, ttc=1.0, ego_speed=10.0, n_cars=3, p_pedestrian=1.0, p_car=1.0)
        actors, _ = place(spec, draw)
        sides.add(float(np.sign(actors.car_vel[0, 1])))
        ped_sides.add(float(np.sign(actors.ped_vel[0, 1])))
        lanes |= {float(y) for y in actors.car_xy[1:4, 1]}
    assert sides == ped_sides == {-1.0, 1.0}
    assert lanes == {EGO_LANE_Y, ONCOMING_LANE_Y}


def test_a_crossing_pedestrian_stops_once_past_its_stop_and_traffic_moves_on():
    actors = Actors.empty(collision_point=(10.0, EGO_LANE_Y))
    assert actors.collision_point == (10.0, EGO_LANE_Y)
    for name in ("car_active", "car_hazard", "ped_active", "ped_hazard"):
        assert getattr(actors, name).dtype == bool and not getattr(actors, name).any(), name
    assert np.isnan(actors.ped_stop_y).all() and not actors.car_xy.any() and not actors.ped_vel.any()
    assert actors.car_xy.shape == (CAR_POOL, 2) and actors.ped_xy.shape == (PEDESTRIAN_POOL, 2)
    assert actors.car_heading.shape == (CAR_POOL,) and not actors.car_heading.any()
    assert Actors.empty().collision_point is None
    actors.car_vel[0] = (3.0, -2.0)
    actors.ped_xy[0], actors.ped_vel[0], actors.ped_stop_y[0] = (5.0, -4.0), (0.5, 2.0), 1.0  # walking towards +y
    actors.ped_xy[1], actors.ped_vel[1], actors.ped_stop_y[1] = (0.0, 4.0), (0.0, -1.0), 1.0  # towards -y
    actors.advance(1.0)
    actors.advance(1.0)  # y = 0 and 2: neither past its stop yet
    assert actors.car_xy[0].tolist() == [6.0, -4.0]
    assert actors.ped_xy[:2].tolist() == [[6.0, 0.0], [0.0, 2.0]] and actors.ped_stop_y[:2].tolist() == [1.0, 1.0]
    actors.advance(1.0)  # 2.0, past its stop: it stands; the other is exactly at its stop, and walks on
    assert actors.ped_vel[0].tolist() == [0.0, 0.0] and np.isnan(actors.ped_stop_y[0])
    assert actors.ped_vel[1].tolist() == [0.0, -1.0] and actors.ped_stop_y[1] == 1.0
    actors.advance(1.0)
    assert actors.ped_xy[0].tolist() == [6.5, 2.0]  # standing still
    assert actors.ped_xy[1].tolist() == [0.0, 0.0] and actors.ped_vel[1].tolist() == [0.0, 0.0]
    assert np.isnan(actors.ped_stop_y[1]) and actors.car_xy[0].tolist() == [12.0, -8.0]


def test_traffic_draws_span_their_documented_ranges():
    """Over 300 seeded scenarios with full traffic, every random placement reaches the ends of its range and no
    further, and every coin comes up both ways: the ranges above are the ranges drawn, not just bounds."""
    draws: dict[str, list[float]] = {k: [] for k in ("first_same", "same_gap", "factor", "oncoming_x0", "oncoming_gap")}
    draws |= {k: [] for k in ("oncoming_speed", "junction_x", "stroller_x", "stroller_y", "stroller_speed")}
    signs: dict[str, set] = {"stroller_side": set(), "stroller_way": set()}
    for draw in range(300):
        spec = ScenarioSpec(seed=draw, ttc=1.0, ego_speed=10.0, n_cars=10, n_pedestrians=10)
        actors, junction_x = place(spec, draw)
        bumper = EGO_X0 + EGO_FRONT + spec.ego_speed * spec.ttc
        draws["junction_x"].append(junction_x)
        cars = range(spec.n_cars)
        same = sorted(actors.car_xy[i, 0] for i in cars if actors.car_xy[i, 1] == EGO_LANE_Y)
        oncoming = [actors.car_xy[i, 0] for i in cars if actors.car_xy[i, 1] == ONCOMING_LANE_Y]
        if same:
            draws["first_same"].append(same[0] - bumper)
            draws["same_gap"] += [b - a - CAR_LENGTH for a, b in zip(same, same[1:])]
            draws["factor"] += [
                actors.car_vel[i, 0] / spec.ego_speed for i in cars if actors.car_xy[i, 1] == EGO_LANE_Y
            ]
        if oncoming:
            assert oncoming == sorted(oncoming)  # placed one after the other, from behind the ego forwards
            draws["oncoming_x0"].append(oncoming[0] - EGO_X0)
            draws["oncoming_gap"] += [b - a - CAR_LENGTH for a, b in zip(oncoming, oncoming[1:])]
            draws["oncoming_speed"] += [-actors.car_vel[i, 0] for i in cars if actors.car_xy[i, 1] == ONCOMING_LANE_Y]
        for i in range(spec.n_pedestrians):
            (x, y), vx = actors.ped_xy[i], actors.ped_vel[i, 0]
            draws["stroller_x"].append(x - EGO_X0)
            draws["stroller_y"].append(abs(y))
            draws["stroller_speed"].append(abs(vx))
            signs["stroller_side"].add(float(np.sign(y)))
            signs["stroller_way"].add(float(np.sign(vx)))
    ranges = {
        "first_same": (15.0, 35.0),  # beyond the collision point
        "same_gap": (8.0, 40.0),
        "factor": (1.0, 1.2),  # never slower than the ego
        "oncoming_x0": (-20.0, -5.0),
        "oncoming_gap": (8.0, 40.0),
        "oncoming_speed": (6.0, 14.0),
        "junction_x": (30.0, 150.0),
        "stroller_x": (-10.0, 150.0),
        "stroller_y": (4.3, 6.0),
        "stroller_speed": (0.8, 1.8),
    }
    for name, (lo, hi) in ranges.items():
        values, tol = np.array(draws[name]), 0.01 * (hi - lo)
        assert lo - 1e-9 <= values.min() < lo + tol and hi - tol < values.max() <= hi + 1e-9, (
            name,
            values.min(),
            values.max(),
        )
    assert signs["stroller_side"] == signs["stroller_way"] == {-1.0, 1.0}


def test_the_crossing_pedestrian_starts_from_the_near_sidewalk_half_the_time_when_the_walk_fits():
    """The rule: from the right (the near side, -y) only when the start, reach metres back along the walk from the
    meeting point, is no further out than 0.2 m inside the near sidewalk's outer edge; then a fair coin. Each draw's
    would-be right start is rebuilt from where it meets the bumper and the angle it walks at."""
    fits_right, fits_left, near_edge, near_edge_askew = 0, 0, [], []
    for draw in range(600):
        spec = ScenarioSpec(
            seed=draw, ttc=1.5, ego_speed=10.0, pedestrian_speed=1.0 + 3.5 * (draw % 7) / 6, p_pedestrian=1.0
        )
        actors, _ = place(spec, draw)
        xy, vel = actors.ped_xy[0], actors.ped_vel[0]
        reach = spec.pedestrian_speed * spec.ttc
        meet_y = xy[1] + vel[1] * spec.ttc
        cos = math.sqrt(max(0.0, 1.0 - (vel[0] / spec.pedestrian_speed) ** 2))
        right_start = meet_y - reach * cos
        from_right = vel[1] > 0  # walking towards +y: it came from the right
        if right_start >= -(SIDEWALK_OUTER - 0.2):
            fits_right += from_right
            fits_left += not from_right
            if from_right:
                near_edge.append(right_start)
                if cos < math.cos(math.radians(20.0)):  # the rule measures the walk across, not along its path
                    near_edge_askew.append(right_start)
        else:
            assert not from_right, (draw, right_start)
    assert fits_right + fits_left > 200 and 0.4 < fits_right / (fits_right + fits_left) < 0.6
    # right starts go all the way to the allowed edge, those walking at a slant too
    assert min(near_edge) < -(SIDEWALK_OUTER - 0.2) + 0.3 and min(near_edge_askew) < -(SIDEWALK_OUTER - 0.2) + 0.3
