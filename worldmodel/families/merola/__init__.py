"""Merola et al. 2022 on our simulator: a DDQN on camera frames that brakes and steers, on family ``merola``.
What it runs is ``system.py``."""

from ...registry import Family
from .config import MerolaAgentConfig, MerolaEvalConfig

FAMILY = Family(
    name="merola",
    system="worldmodel.families.merola.system",
    rewards=("merola", "merola_safe"),  # the paper's, and the deviation the diagnosis names
    validation_seeds=(2022, 77),
    sealed_seed=17734,
    suite_test_seed=61004,
    preset="ddqn_merola",
    section="merola",
    agent_config=MerolaAgentConfig,
    eval_config=MerolaEvalConfig,
    learners=("dqn", "counterfactual"),  # its DDQN, and the nine-action learner (counterfactual.py)
    observations=("frames_vae", "frames_resnet", "privileged"),
    hashed_as={"resnet_weights": "resnet_weights", "total_steps": "peer_total_steps"},
    hashed_defaults={"resnet_weights": None},
)
