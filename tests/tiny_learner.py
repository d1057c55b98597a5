"""A learner that exists only in the tests, added by the steps of docs/design.md §11 ("How to add a learner") and
nothing else: it learns one constant action, the mean of the planner's first actions over a few scenarios it drives,
and acts with it from the start of every episode.

Everything the learner needs is in this file: its declaration, its training (``run``), the policy rebuilt from its
checkpoint (``build_policy``) and the agent preset that trains it. ``registered()`` is the one line per registry
that a real learner adds to ``worldmodel/registry.py`` and ``conf/agent/``, undone when the test is over.
"""

from __future__ import annotations

import contextlib

import numpy as np
from hydra.core.config_store import ConfigStore

from worldmodel import registry

NAME = "tiny_constant"
LEARNER = registry.Learner(NAME, sees=("worldmodel",), module=__name__)
PRESET = {"agent": {"variant": "tiny_constant", "learner": NAME, "rewards": ["r2"]}}


def run(cfg, agent_id) -> dict:
    """Drive the privileged planner on a few training scenarios and keep the mean of its first actions."""
    from envs import rollout, sample_scenario
    from envs.planner import PrivilegedPlanner
    from worldmodel import artifacts
    from worldmodel.common import make_env
    from worldmodel.config import oracle_settings
    from worldmodel.training import TrainingRun

    with TrainingRun(cfg, "train_agent", agent_id.dir(cfg), artifacts.provenance(cfg, "agent")) as run_:
        env, planner, first = make_env(cfg, camera=False), PrivilegedPlanner.from_settings(**oracle_settings(cfg)), []
        for k in range(3):
            spec = sample_scenario(np.random.default_rng([cfg.seed, k]))
            rollout(env, planner, spec, on_step=lambda obs, action, reward, info: first.append(action), max_steps=1)
        env.close()
        action = [float(v) for v in np.mean(first, axis=0)]
        run_.save({"learner": NAME, "obs": "worldmodel", "obs_dim": 0, "use_speed": False, "action": action})
        return run_.finish({"reward": agent_id.reward, "learner": NAME, "action": action})


class ConstantPolicy:
    needs_camera = False  # it reads nothing

    def __init__(self, name: str, action):
        self.name, self.action = name, np.asarray(action, np.float32)

    def reset(self, seed: int | None = None) -> None:
        pass

    def act(self, obs, info) -> np.ndarray:
        return self.action


def build_policy(name: str, encoder, state: dict, device="cpu") -> ConstantPolicy:
    return ConstantPolicy(name, state["action"])


@contextlib.contextmanager
def registered():
    """The learner's one line in each registry, taken back afterwards."""
    registry.register_learner(LEARNER)
    ConfigStore.instance().store(group="agent", name=PRESET["agent"]["variant"], node=PRESET, package="_global_")
    try:
        yield LEARNER
    finally:
        ConfigStore.instance().repo["agent"].pop(f"{PRESET['agent']['variant']}.yaml", None)
        registry.unregister_learner(NAME)
