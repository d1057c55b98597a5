"""The camera's views (conf/view/; docs/design.md §3): the paper's one sample per pixel, road users drawn
pixel-conservatively (``road_user_cover``), and its reference, rendering at k× and pooling (``supersample``).

A known scene: the paper's street with no traffic, and one pedestrian placed straight ahead of the ego at a chosen
distance and lateral offset. What each view must show there is computed here by hand, with a pinhole model of the
camera written independently of ``envs/camera.py``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from envs import UrbanCollisionEnv
from envs.actors import CAR_POOL, PEDESTRIAN_HALF_SIZE, PEDESTRIAN_POOL
from envs.camera import EYE_FORWARD, EYE_HEIGHT, PITCH_DEG
from envs.scenario import ScenarioSpec
from envs.scene import PEDESTRIANS, ROADS, SIDEWALK_HEIGHT, VEHICLES
from worldmodel.config import compose

VIEWS = {"paper64": {}, "cover64": {"road_user_cover": True}, "pool8": {"supersample": 8}}
SIZE = 64


@pytest.fixture(scope="module")
def scene():
    """One env per view, reset to the same empty street; yields a function that places the pedestrian and renders."""
    made = {name: UrbanCollisionEnv(camera=True, **kw) for name, kw in VIEWS.items()}
    spec = ScenarioSpec(seed=3, ttc=1.0, ego_speed=10.0)
    for env in made.values():
        env.reset(options={"scenario": spec})

    def render(name: str, ahead_m: float, left_m: float, car_heading: float | None = None) -> np.ndarray:
        """The pedestrian (or, with ``car_heading`` in radians, a car) ``ahead_m`` forward of the eye and ``left_m``
        to its left; the view's frame."""
        env = made[name]
        ego = env.ego
        c, s = math.cos(ego.psi), math.sin(ego.psi)
        eye = (ego.x + EYE_FORWARD * c, ego.y + EYE_FORWARD * s)
        at = (eye[0] + ahead_m * c - left_m * s, eye[1] + ahead_m * s + left_m * c)
        peds, ped_on = np.zeros((PEDESTRIAN_POOL, 2)), np.zeros(PEDESTRIAN_POOL, dtype=bool)
        cars, car_on, heading = np.zeros((CAR_POOL, 2)), np.zeros(CAR_POOL, dtype=bool), np.zeros(CAR_POOL)
        if car_heading is None:
            peds[0], ped_on[0] = at, True
        else:
            cars[0], car_on[0], heading[0] = at, True, ego.psi + car_heading
        env._pool.place_actors(cars, heading, car_on, peds, ped_on)
        return env._camera.render(ego.x, ego.y, ego.psi)

    yield render
    for env in made.values():
        env.close()


def pinhole_box(ahead_m: float, left_m: float) -> tuple[float, float, float, float]:
    """(u0, u1, w0, w1): the screen extent of the pedestrian's front face, in pixel units of a 64-px frame (pixel
    column c spans u in [c, c + 1), row r spans w in [r, r + 1)). Facing the camera, the face nearest it bounds the
    whole box's outline (the box's top is above the eye, so its far top edge projects lower)."""
    hx, hy, hz = PEDESTRIAN_HALF_SIZE
    p = math.radians(PITCH_DEG)
    f = 0.5 * SIZE / math.tan(math.radians(45.0))  # the 90-degree field across 64 px
    a = ahead_m - hx  # the front face, forward of the eye

    def project(lateral: float, up: float) -> tuple[float, float]:
        depth = a * math.cos(p) - up * math.sin(p)
        camera_up = a * math.sin(p) + up * math.cos(p)
        return 0.5 * SIZE - f * lateral / depth, 0.5 * SIZE - f * camera_up / depth

    bottom, top = SIDEWALK_HEIGHT - EYE_HEIGHT, SIDEWALK_HEIGHT + 2 * hz - EYE_HEIGHT
    corners = [project(left_m + dy, h) for dy in (-hy, hy) for h in (bottom, top)]
    us, ws = zip(*corners, strict=True)
    return min(us), max(us), min(ws), max(ws)


def covered(u0: float, u1: float, w0: float, w1: float) -> int:
    """Pixels a rectangle covers in part (pixel c spans [c, c + 1))."""
    return (math.ceil(u1) - math.floor(u0)) * (math.ceil(w1) - math.floor(w0))


@pytest.mark.parametrize(("ahead_m", "left_m"), [(10.0, 0.13), (20.0, -0.41), (30.0, 0.13), (40.0, 0.77)])
def test_a_pedestrian_covers_the_pixels_a_pinhole_camera_predicts(scene, ahead_m, left_m):
    box = pinhole_box(ahead_m, left_m)
    frame = scene("cover64", ahead_m, left_m)
    rows, cols = np.nonzero(frame == PEDESTRIANS)
    assert (frame == PEDESTRIANS).sum() == covered(*box), (box, rows, cols)
    assert cols.min() == math.floor(box[0]) and cols.max() == math.ceil(box[1]) - 1
    assert rows.min() == math.floor(box[2]) and rows.max() == math.ceil(box[3]) - 1
    assert (frame[-4:, 28:36] == ROADS).all()  # the road ahead, in every view
    for name in ("paper64", "pool8"):
        assert (scene(name, ahead_m, left_m)[-4:, 28:36] == ROADS).all()


def test_the_paper_frame_loses_a_pedestrian_narrower_than_a_pixel_and_the_other_views_keep_it(scene):
    """40 m ahead, 0.6 m wide is ~0.5 px: placed between two columns' sample points, TinyRenderer's one sample per
    pixel misses it. Pooling a render at 8x keeps it; the cover keeps at least those pixels, and at most a
    one-pixel border more."""
    ahead = 40.0
    # the pedestrian's centre half-way between the sample points of columns 30 and 31
    left = (0.5 * SIZE - 30.5) * (ahead - PEDESTRIAN_HALF_SIZE[0]) * math.cos(math.radians(PITCH_DEG)) / (0.5 * SIZE)
    u0, u1, _, _ = pinhole_box(ahead, left)
    assert 30.0 < u0 < u1 < 31.0  # between the sample points, so the setting is what the test says
    paper, pooled, cover = (scene(name, ahead, left) for name in ("paper64", "pool8", "cover64"))
    assert (paper == PEDESTRIANS).sum() == 0
    assert (pooled == PEDESTRIANS).sum() >= 1
    assert ((pooled == PEDESTRIANS) & (cover != PEDESTRIANS)).sum() == 0
    assert ((cover == PEDESTRIANS) & ~grown_by_one(pooled == PEDESTRIANS)).sum() == 0
    # everything but the road user is the paper's frame, pixel for pixel
    others = (paper != PEDESTRIANS) & (cover != PEDESTRIANS) & (pooled != PEDESTRIANS)
    np.testing.assert_array_equal(cover[others], paper[others])
    np.testing.assert_array_equal(pooled[others], paper[others])


def grown_by_one(mask: np.ndarray) -> np.ndarray:
    out = np.zeros_like(mask)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            out |= np.roll(mask, (dr, dc), axis=(0, 1))
    return out


@pytest.mark.parametrize("heading_deg", [30.0, 45.0, 70.0])
def test_a_turned_car_is_covered_by_its_outline_not_its_bounding_box(scene, heading_deg):
    """A car turned across the view projects to a slanted hexagon, whose screen bounding box holds pixels it never
    touches. The cover holds every pixel that pooling a render at 8x holds and adds no pixel outside a one-pixel
    border of them; at the corners of the slanted outline a bounding box would."""
    pooled = scene("pool8", 9.0, -2.0, math.radians(heading_deg)) == VEHICLES
    cover = scene("cover64", 9.0, -2.0, math.radians(heading_deg)) == VEHICLES
    assert pooled.sum() >= 4
    assert (pooled & ~cover).sum() == 0
    assert (cover & ~grown_by_one(pooled)).sum() == 0
    rows, cols = np.nonzero(cover)
    box = (rows.max() - rows.min() + 1) * (cols.max() - cols.min() + 1)
    assert cover.sum() < box  # the outline, not its box


def test_covered_frames_differ_from_the_paper_frames_only_by_road_users():
    """Through real episodes with traffic: the cover only ever adds road users (pedestrians over vehicles, never the
    reverse), the rest of the frame is the paper's, and the pixels the paper shows a pedestrian on stay one."""
    spec = ScenarioSpec(seed=9, ttc=1.2, ego_speed=20.0, n_cars=6, n_pedestrians=8, p_pedestrian=1.0, p_car=1.0)
    paper, cover = UrbanCollisionEnv(), UrbanCollisionEnv(road_user_cover=True)
    try:
        a, _ = paper.reset(options={"scenario": spec})
        b, _ = cover.reset(options={"scenario": spec})
        added = 0
        for _ in range(12):
            road_user = np.isin(b["seg"], (PEDESTRIANS, VEHICLES))
            np.testing.assert_array_equal(a["seg"][~road_user], b["seg"][~road_user])
            assert (b["seg"][a["seg"] == PEDESTRIANS] == PEDESTRIANS).all()
            added += int(road_user.sum() - np.isin(a["seg"], (PEDESTRIANS, VEHICLES)).sum())
            a = paper.step(np.array([0.0, -1.0], np.float32))[0]
            b = cover.step(np.array([0.0, -1.0], np.float32))[0]
        assert added > 0
    finally:
        paper.close()
        cover.close()


def test_the_views_are_config_groups_and_the_paper_view_is_the_default():
    plain = compose("collect", ["experiment=x"])
    assert not plain.env.road_user_cover and plain.env.supersample == 1
    assert compose("collect", ["experiment=x", "view=paper64"]).env == plain.env
    assert compose("collect", ["experiment=x", "view=cover64"]).env.road_user_cover
    assert compose("collect", ["experiment=x", "view=pool64"]).env.supersample == 4
    with pytest.raises(ValueError, match="supersample"):
        UrbanCollisionEnv(camera=False, supersample=0)


def test_the_committed_view_sweep_is_what_its_command_computes():
    """docs/results/views/: the pixels per view from the simulator, and the sweep's table from the committed rows
    and probe results, as ``python -m experiments.view_sweep pixels|figure`` write them."""
    import json

    from experiments import view_sweep

    committed = json.loads((view_sweep.OUT / "pixels.json").read_text())
    assert view_sweep.measure_pixels(committed["per_cell"]) == committed
    assert committed["views"]["paper64"]["none_share"] > 0.3 and committed["views"]["cover64"]["none_share"] == 0.0
    seen = json.loads((view_sweep.OUT / "visibility.json").read_text())
    assert view_sweep.measure_visibility(seen["per_cell"], seen["frames_per_scenario"]) == seen
    assert (view_sweep.OUT / "sweep.md").read_text() == view_sweep.HEADER + view_sweep.figure(plot=False)


# The paper view's frames of nine scenarios of bank 2018 (onset and five steps of braking while steering), hashed as the
# camera drew them before views existed. The default view must stay these bytes: every recorded dataset and world
# model was made from them.
PAPER_FRAMES_HASH = "7e25d616cbf0f9031b43da70509a2116ca39b84752b8a784480f288d33583c7e"


def test_the_paper_view_draws_the_frames_it_drew_before_views_existed():
    import hashlib

    from envs import scenario_bank
    from worldmodel.common import make_env

    env = make_env(compose("collect", ["experiment=x"]))  # the default view, as every stage builds it
    h = hashlib.sha256()
    try:
        for entry in scenario_bank(per_cell=1, seed=2018)[::7]:
            obs, _ = env.reset(options={"scenario": entry.spec})
            h.update(obs["seg"].tobytes())
            for _ in range(5):
                obs = env.step(np.array([0.3, -1.0], np.float32))[0]
                h.update(obs["seg"].tobytes())
    finally:
        env.close()
    assert h.hexdigest() == PAPER_FRAMES_HASH


def test_the_perception_probe_reads_the_frames_of_the_view_it_is_given(tmp_path):
    """``experiments.perception_probe view=cover64 --perception-only`` at smoke size: labels of that view in a store
    of their own, the R² of every hazard-state field written, no planner's rows needed."""
    import json

    from envs.chooser import HAZARD_STATE
    from experiments import perception_probe
    from worldmodel import chooser_labels

    base = [f"paths.data_root={tmp_path}/data", f"paths.runs_root={tmp_path}/runs", "experiment=t", "scale=smoke"]
    args = [*base, "view=cover64", "agent.chooser.episodes=6", "--steps", "3", "--threads", "1", "--perception-only"]
    assert perception_probe.main(args) == 0
    written = json.loads((tmp_path / "runs/t/perception_probe/r2.json").read_text())
    assert set(written["r2"]) == set(HAZARD_STATE) and written["steps"] == 3 and written["camera"] == "wide"
    assert sum(band["frames"] for band in written["r2_by_speed"].values()) == len(
        np.load(tmp_path / "runs/t/perception_probe/validation.npz")["speed"]
    )
    cover = chooser_labels.labels_dir(compose("train_agent", [*base, "view=cover64", "agent=chooser"]))
    paper = chooser_labels.labels_dir(compose("train_agent", [*base, "agent=chooser"]))
    assert cover.exists() and cover != paper


def test_the_perception_probe_reads_the_second_cameras_frames_when_asked(tmp_path):
    import json

    from experiments import perception_probe

    base = [f"paths.data_root={tmp_path}/data", f"paths.runs_root={tmp_path}/runs", "experiment=t", "scale=smoke"]
    args = [
        *base,
        "agent.chooser.episodes=6",
        "--steps",
        "3",
        "--threads",
        "1",
        "--perception-only",
        "--camera",
        "tele",
    ]
    with pytest.raises(SystemExit, match="tele_fov_deg"):
        perception_probe.main(args)
    assert perception_probe.main(["env.tele_fov_deg=30", *args]) == 0
    written = json.loads((tmp_path / "runs/t/perception_probe/r2.json").read_text())
    assert written["camera"] == "tele" and written["rows"] == [8, 48]
