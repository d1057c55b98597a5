"""Kim et al. 2020 on our simulator: DDPG with a LIDAR front end against red-light runners, on family ``kim``.
What it runs is ``system.py`` (the package's modules by job are listed there)."""

from ...registry import Family
from .config import KimAgentConfig, KimEvalConfig

FAMILY = Family(
    name="kim",
    system="worldmodel.families.kim.system",
    rewards=("kim_unaware", "kim_aware"),
    validation_seeds=(2020, 77),
    sealed_seed=53799,
    suite_test_seed=61003,
    preset="ddpg_kim",
    section="kim",
    agent_config=KimAgentConfig,
    eval_config=KimEvalConfig,
    observations=("lidar", "privileged"),
    hashed_as={
        "impact_offset_spread": "kim_impact_offset_spread",
        "bc_steer_weight": "bc_steer_weight",
        "total_steps": "peer_total_steps",
    },
    hashed_defaults={"kim_impact_offset_spread": 0.0, "bc_steer_weight": 1.0, "peer_total_steps": 100_000},
)
