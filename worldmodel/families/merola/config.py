"""Family merola's config sections: ``agent.merola`` (its DDQN's training) and ``evaluate.merola``. The family
declares them (``Family.agent_config``, ``eval_config``); the schema has them from the registry."""

from __future__ import annotations

from dataclasses import dataclass, field

from ...banks import seed_problems
from ...common import Checked, ConfigValueError
from ...common import positive_fields as _positive


@dataclass
class MerolaAgentConfig(Checked):
    """Merola et al.'s DDQN (``agent=ddqn_merola``, family merola; worldmodel/families/merola/system.py)."""

    # environment steps of training, whole episodes (the paper: 360k); a key of its own, so that a scale can shrink
    # it while the preset keeps the paper's other settings. 100k: what two cores afford (docs/results/merola/)
    total_steps: int = 100_000
    # obs=frames_resnet: a local ResNet-18 state dict with torchvision's names (ImageNet weights cannot be
    # downloaded here; worldmodel/models/resnet.py refuses to run without them)
    resnet_weights: str | None = None

    def agent_problems(self, agent):
        """Checks against the agent's other keys (``agent``, the whole agent section)."""
        yield from agent.total_steps_problems("merola.total_steps", self.total_steps)


SCRIPTED = (
    "braking",
    "aeb3m",
    "oracle",
    "hold",
    "brake_release",
    "brake_stop",
)  # the scripted policies its evaluation runs


@dataclass
class MerolaEvalConfig(Checked):
    """Merola et al.'s scenarios (worldmodel/families/merola/): collision rate, ego delta-v, injury risk and return
    per scenario for braking, the planner, the paper's world-model agents and every ddqn_merola agent."""

    trials: int = 100  # seeded trials per scenario, the same for every policy
    # straight-line braking from the start, Kim's AEB-3m (brakes once a footprint is within 3 m ahead), the planner;
    # also hold (drives on), brake_release and brake_stop (brake, let go below the reward's v_min or at a
    # standstill), to read the reward against
    policies: list[str] = field(default_factory=lambda: ["braking", "aeb3m", "oracle"])
    world_model_agents: bool = True  # also the paper's R1 / R2 agents and the chooser, at their own 1/15 s steps
    seed: int = 2022  # the validation draw (evaluate.bank=validation); the test draw is worldmodel/banks.py's

    def problems(self):
        yield from _positive(self, "trials")
        yield from seed_problems(self, "seed", "merola.")
        if any(p not in SCRIPTED for p in self.policies):
            yield ConfigValueError("policies", list(self.policies), f"use some of {', '.join(SCRIPTED)}")
