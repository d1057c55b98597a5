"""What a dqn agent on family chae sees, and the family's env: Chae's pedestrian history (privileged, the paper's)
or our world model's view of the camera frame, at the paper's 0.1 s steps."""

from __future__ import annotations

import numpy as np

from envs.chae import STEP_S, PedestrianHistory

from ... import loading
from ...common import make_env
from . import FAMILY as DECLARED

FAMILY, PRESET = DECLARED.name, DECLARED.preset  # as the package declares them
NCAP_REWARD = "chae"  # the reward its env reports on the Euro NCAP bank
# Chae's state to roughly unit scale: dx up to ~85 m, dy up to ~6 m, speed up to ~17 m/s
HISTORY_SCALE = np.tile(np.array([1 / 50.0, 1 / 4.0, 1 / 20.0], np.float32), PedestrianHistory.steps)


class HistoryObserver:
    """Chae's 15-value pedestrian history, scaled (privileged; no camera)."""

    camera = False
    dim = PedestrianHistory.dim

    def __init__(self, noise_m: float = 0.1):
        self.view = PedestrianHistory(noise_m)

    def reset(self, seed: int | None) -> None:
        self.view.reset(seed)

    def __call__(self, env, obs) -> np.ndarray:
        return self.view(env) * HISTORY_SCALE

    def note_action(self, action) -> None:
        pass


class WorldModelObserver:
    """The world model's agent input from the camera frame (``agent_obs.WorldModelEncoder``)."""

    camera = True

    def __init__(self, encoder):
        self.encoder, self.dim = encoder, encoder.dim

    def reset(self, seed: int | None) -> None:
        self.encoder.reset()

    def __call__(self, env, obs) -> np.ndarray:
        return self.encoder.encode(obs)

    def note_action(self, action) -> None:
        self.encoder.note_action(action)


def observer(cfg, obs: str, noise_m: float | None = None):
    """What a dqn agent sees; Chae's state with ``noise_m`` (default: ``agent.chae.noise_m``, training's, a float
    in the schema)."""
    if obs == "pedestrian_history":
        return HistoryObserver(cfg.agent.chae.noise_m if noise_m is None else noise_m)
    return WorldModelObserver(loading.load_world_model(cfg, use_speed=True, frame_view=False))


def family_env(cfg, camera: bool, end_on_bump: bool = True):
    """Family chae's env at the paper's 0.1 s steps, whatever ``env.step_s`` the stage was given (``evaluate
    evaluate.family=chae`` does not load the agent preset that sets it); ``end_on_bump=False`` (evaluation) records
    the bump and runs on, to measure contact."""
    options = {} if end_on_bump else {"family_options": {"end_on_bump": False}}
    return make_env(cfg, camera=camera, family="chae", reward="chae", step_s=STEP_S, **options)
