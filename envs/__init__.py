"""The pybullet urban imminent-collision simulator (numpy, pybullet and gymnasium only; never torch).

``import envs`` registers ``UrbanCollision-v0``::

    env = gymnasium.make("UrbanCollision-v0", camera=True, reward="r2")
    obs, info = env.reset(options={"scenario": ScenarioSpec(seed=1, ttc=0.8, ego_speed=20.0, p_pedestrian=1.0)})
"""

from gymnasium.envs.registration import register, registry

from .env import DT, UrbanCollisionEnv
from .injury import occupant_injury, pedestrian_injury
from .policies import NoisyAutopilot, StraightLineBraking
from .rollout import Episode, rollout
from .scenario import BankEntry, ScenarioSpec, sample_focus_scenario, sample_scenario, scenario_bank
from .scene import CLASS_NAMES, NUM_CLASSES, PALETTE

ENV_ID = "UrbanCollision-v0"
if ENV_ID not in registry:
    register(id=ENV_ID, entry_point="envs.env:UrbanCollisionEnv")

__all__ = [
    "CLASS_NAMES",
    "DT",
    "ENV_ID",
    "NUM_CLASSES",
    "PALETTE",
    "BankEntry",
    "Episode",
    "NoisyAutopilot",
    "ScenarioSpec",
    "StraightLineBraking",
    "UrbanCollisionEnv",
    "occupant_injury",
    "pedestrian_injury",
    "rollout",
    "sample_focus_scenario",
    "sample_scenario",
    "scenario_bank",
]
