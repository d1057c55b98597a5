"""Chae et al. 2017 on our simulator: DQN braking with a trauma memory, trained and evaluated on family ``chae``.
What it runs is ``system.py`` (the package's modules by job are listed there)."""

from ...registry import Family
from .config import ChaeAgentConfig, ChaeEvalConfig

FAMILY = Family(
    name="chae",
    system="worldmodel.families.chae.system",
    rewards=("chae",),
    # 101-115: the fresh draws its investigation judged single configurations on (docs/results/chae/notes/)
    validation_seeds=(2017, 99, 98, *range(101, 116)),
    sealed_seed=88384,
    suite_test_seed=61002,
    preset="dqn_chae",
    section="chae",
    agent_config=ChaeAgentConfig,
    eval_config=ChaeEvalConfig,
    learners=("dqn",),
    ensemble_key="evaluate.chae.ensemble",
    selects_checkpoints=True,
    hashed_as={"episodes": "episodes", "ttc_range": "chae_ttc_range", "noise_m": "chae_noise_m", "select": "select"},
    hashed_defaults={"episodes": 3000, "chae_ttc_range": [1.5, 4.0], "chae_noise_m": 0.1},
    removed_eval_keys={"ensemble_pool": 0, "ensemble_vote": False},
)
