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
