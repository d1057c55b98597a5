"""What Kim et al.'s agent sees on family ``kim``: the LIDAR observer, the family's env and the scenarios of its
training distribution."""

from __future__ import annotations

import math

import numpy as np

from envs.kim import KimSpec
from envs.kim import sample as sample_kim
from envs.lidar import RANGE_M, LidarHistory

from ...common import StageError, make_env
from . import FAMILY as DECLARED

FAMILY, PRESET = DECLARED.name, DECLARED.preset  # as the package declares them
NCAP_REWARD = "kim_unaware"  # the reward its env reports on the Euro NCAP bank
GOAL_REWARDS = ("kim_aware",)  # rewards whose agent also sees the goal (Kim et al. §II-F)


class LidarObserver:
    """Kim's observation: ``scans`` LIDAR scans of ``rays`` rays (the paper: 4 of 36) and the previous action
    (``envs.lidar.LidarHistory``), plus, for the goal-aware agent, the distance to the goal (/ 50 m) and its
    bearing from the heading (/ pi). The agent's ``lidar_scans`` and ``lidar_rays`` set both, so the encoder reads
    the scans it is given. ``speed`` (``agent.use_speed``; not the paper's) also appends the ego's speed / 20 m/s,
    which the scans only show as the change between them."""

    camera = False

    def __init__(self, goal: bool, scans: int = 4, rays: int = 36, speed: bool = False):
        self.history, self.goal, self.speed = LidarHistory(scans=scans, n_rays=rays), bool(goal), bool(speed)
        self.dim = self.history.dim + (2 if self.goal else 0) + (1 if self.speed else 0)

    def reset(self, seed=None) -> None:
        self.history.reset(seed)

    def note_action(self, action) -> None:
        self.history.note_action(action)

    def __call__(self, env, obs=None) -> np.ndarray:
        parts, ego = [self.history(env)], env.ego
        if self.goal:
            gx, gy = env.family_state.goal
            bearing = math.atan2(gy - ego.y, gx - ego.x) - ego.psi
            bearing = (bearing + math.pi) % (2 * math.pi) - math.pi
            d = min(1.0, math.hypot(gx - ego.x, gy - ego.y) / RANGE_M)
            parts.append(np.array([d, bearing / math.pi], np.float32))
        if self.speed:
            parts.append(np.array([ego.v / 20.0], np.float32))
        return np.concatenate(parts)


def observer(cfg, reward: str):
    """The LIDAR observer of the agent section of ``cfg`` (or, with ``agent.obs=privileged``, the true state,
    ``TrueStateView``): the typed config (``validate(cfg)``) or the composed one,
    whose schema gives the same typed values."""
    a = cfg.agent
    if a.obs == "privileged":  # the diagnosis: the same learner on the true state
        from ..common import TrueStateView

        return TrueStateView()
    if a.obs != "lidar":
        raise StageError(
            f"Kim et al.'s agent (agent=ddpg_kim) sees the LIDAR (obs=lidar), not obs={a.obs}; the camera "
            "agent on this family is agent=ddpg_wm_kim"
        )
    return LidarObserver(reward in GOAL_REWARDS, a.lidar_scans, a.lidar_rays, a.use_speed)


def family_env(cfg, reward: str, camera: bool = False, step_s: float = 0.1):
    return make_env(cfg, camera=camera, family="kim", reward=reward, step_s=step_s)


def training_scenario(cfg, *stream: int, seed: int | None = None) -> KimSpec:
    """A scenario of the training distribution (``agent.kim.impact_offset_spread`` says where the runner may
    strike), a function of (seed, ``stream``) only, so a resumed run draws what an uninterrupted one would;
    ``stream`` starts with a tag of envs/streams.py (``KIM_TRAINING_EPISODES`` and the others) and its indices;
    ``seed``: another than the training seed (labels shared by every seed). ``cfg``: the typed config
    (``validate(cfg)``; called once per episode, so the caller validates) or the composed one, whose schema gives
    the same int seed and float spread."""
    rng = np.random.default_rng([cfg.seed if seed is None else seed, *map(int, stream)])
    return sample_kim(rng, cfg.agent.kim.impact_offset_spread)


def ddpg_config(cfg):
    """The DDPG config a LIDAR agent of ``cfg`` is built with (``DDPGConfig.of`` its typed agent section)."""
    from ...config import validate
    from ...models.ddpg_config import DDPGConfig

    return DDPGConfig.of(validate(cfg).agent)
