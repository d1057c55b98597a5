"""The agent's view of the raw frame (``envs/views.py``): on real rendered frames, the hazard profiles show the
pedestrian exactly when the camera does, and the previous frame's profiles follow the current ones."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from envs import CLASS_NAMES, ENV_ID, ScenarioSpec
from envs.views import HAZARD_CLASSES, HazardView, profiles

PEDESTRIAN = CLASS_NAMES.index("Pedestrians")


def frames(spec: ScenarioSpec) -> list[np.ndarray]:
    env = gym.make(ENV_ID, camera=True)
    obs, _ = env.reset(options={"scenario": spec})
    out, done = [obs["seg"]], False
    while not done:
        obs, _, terminated, truncated, _ = env.step(np.array([0.0, -1.0], np.float32))
        out.append(obs["seg"])
        done = terminated or truncated
    env.close()
    return out


def test_profiles_show_the_pedestrian_where_the_camera_does():
    crossing = frames(ScenarioSpec(seed=3, ttc=1.0, ego_speed=20.0, p_pedestrian=1.0))
    quiet = frames(ScenarioSpec(seed=3, ttc=1.0, ego_speed=20.0))
    width = crossing[0].shape[1]
    seen = 0
    for seg in crossing:
        p = profiles(seg)
        columns = np.flatnonzero((seg == PEDESTRIAN).any(axis=0))
        np.testing.assert_array_equal(np.flatnonzero(p[:width]), columns)
        seen += bool(len(columns))
    assert seen >= 3  # the crossing pedestrian is in view for several frames before contact
    assert all(profiles(seg)[: 2 * width].sum() == 0 for seg in quiet)  # no hazard: the pedestrian part is empty


def test_the_view_carries_the_previous_frame_and_restarts_at_reset():
    segs = frames(ScenarioSpec(seed=5, ttc=0.8, ego_speed=25.0, p_pedestrian=1.0, p_car=1.0))
    view = HazardView(segs[0].shape[0])
    half = view.dim // 2
    assert half == len(HAZARD_CLASSES) * 2 * segs[0].shape[0]
    first = view(segs[0])
    assert not first[half:].any()
    for prev, seg in zip(segs, segs[1:], strict=False):
        out = view(seg)
        np.testing.assert_array_equal(out[:half], profiles(seg))
        np.testing.assert_array_equal(out[half:], profiles(prev))
    view.reset()
    assert not view(segs[-1])[half:].any()


def test_bad_frames_and_classes_are_clear_errors():
    with pytest.raises(ValueError, match="unknown class names"):
        HazardView(64, ("Pedestrian",))
    with pytest.raises(ValueError, match="square frames"):
        HazardView(64)(np.zeros((32, 32), np.uint8))
    with pytest.raises(ValueError, match=r"\(H, W\) class map"):
        profiles(np.zeros((1, 64, 64), np.uint8))


def test_mask_view_keeps_where_each_class_is_in_the_band():
    """The band holds each class's pixels at their own row and column (what the profiles' marginals lose), then
    the previous frame's; rows outside the band are dropped; bad shapes are refused."""
    from envs.views import MaskView

    view = MaskView(rows=(20, 44))
    seg = np.zeros((64, 64), np.uint8)
    seg[30, 10] = PEDESTRIAN
    seg[25, 50] = CLASS_NAMES.index("Vehicles")
    seg[5, 5] = PEDESTRIAN  # above the band
    first = view(seg).reshape(view.shape)
    assert view.shape == (4, 24, 64)
    assert first[0].sum() == 1 and first[0, 10, 10] == 1  # pedestrians, row 30 -> band row 10
    assert first[1].sum() == 1 and first[1, 5, 50] == 1  # vehicles
    assert first[2:].sum() == 0  # no previous frame yet
    second = view(np.zeros((64, 64), np.uint8)).reshape(view.shape)
    assert second[:2].sum() == 0 and second[2, 10, 10] == 1 and second[3, 5, 50] == 1
    view.reset()
    assert view(seg).reshape(view.shape)[2:].sum() == 0
    with pytest.raises(ValueError, match="class map"):
        view(np.zeros((32, 32), np.uint8))
    with pytest.raises(ValueError, match="rows"):
        MaskView(rows=(40, 20))
