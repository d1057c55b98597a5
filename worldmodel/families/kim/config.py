"""Family kim's config sections: ``agent.kim`` (its LIDAR agents' training) and ``evaluate.kim``. The family
declares them (``Family.agent_config``, ``eval_config``); the schema has them from the registry."""

from __future__ import annotations

from dataclasses import dataclass, field

from envs.kim import CAR_LENGTH

from ...banks import seed_problems
from ...common import Checked, ConfigValueError
from ...common import positive_fields as _positive


@dataclass
class KimAgentConfig(Checked):
    """Kim et al.'s LIDAR agents (``agent=ddpg_kim`` and its variants, family kim; worldmodel/families/kim/)."""

    # environment steps of training (the paper: 100k); a key of its own, so that a scale can shrink it while the
    # preset keeps the paper's other settings
    total_steps: int = 100_000
    # m: training draws the runner's crossing uniformly within this of the ego's middle (envs.kim.sample; the paper
    # does not say); 0 = the middle. Evaluate with the same evaluate.kim.impact_offset_spread
    impact_offset_spread: float = 0.0
    # the cloning loss's weight on labels that steer (|steering| > 0.15 of full); 1 = plain least squares. The
    # planner steers on ~6 % of its labels, and a least-squares student under-steers (docs/results/kim/)
    bc_steer_weight: float = 1.0

    def problems(self):
        if not 0.0 <= self.impact_offset_spread <= CAR_LENGTH / 2:
            yield ConfigValueError(
                "kim.impact_offset_spread",
                self.impact_offset_spread,
                f"it must be in [0, {CAR_LENGTH / 2:g}] m (half the ego)",
            )
        if self.bc_steer_weight <= 0:
            yield ConfigValueError("kim.bc_steer_weight", self.bc_steer_weight, "it must be > 0")

    def agent_problems(self, agent):
        """Checks against the agent's other keys (``agent``, the whole agent section)."""
        yield from agent.total_steps_problems("kim.total_steps", self.total_steps)
        if self.bc_steer_weight != 1.0 and agent.obs != "lidar":
            yield ConfigValueError(
                "kim.bc_steer_weight",
                self.bc_steer_weight,
                "it must be 1 unless the agent sees the LIDAR (obs=lidar)",
            )


@dataclass
class KimEvalConfig(Checked):
    """Kim et al.'s evaluation on family kim (worldmodel/families/kim/): Table 2's avoidance and injury per
    scenario, on the paper's 30 trials per scenario and on ``trials`` with 95 % intervals, and pairwise tests."""

    trials: int = 200  # seeded trials per scenario; the first 30 are the paper-sized table
    paper_trials: int = 30
    # scripted policies beside every LIDAR agent: straight-line braking, Kim's AEB-3m, the planner (the ceiling)
    policies: list[str] = field(default_factory=lambda: ["braking", "aeb3m", "oracle"])
    world_model_agents: bool = True  # also the paper's street-trained R1 / R2 agents and the chooser, as they are
    seed: int = 2020  # the validation draw (evaluate.bank=validation); the test draw is worldmodel/banks.py's
    # m forward of the ego's centre where the runner's path crosses it (envs.kim.KimSpec.impact_offset): 0 the middle
    # (training's), +2.25 the front bumper, -2.25 the rear; the paper does not say
    impact_offset: float = 0.0
    # > 0: each trial's crossing is drawn uniformly within impact_offset ± this (kept on the ego), from a stream of
    # its own, so the trials are otherwise the same; 2.25 with offset 0 = anywhere along the ego
    impact_offset_spread: float = 0.0

    def problems(self):
        yield from _positive(self, "trials", "paper_trials")
        yield from seed_problems(self, "seed", "kim.")
        if not 0.0 <= self.impact_offset_spread <= 4.5:
            yield ConfigValueError("kim.impact_offset_spread", self.impact_offset_spread, "it must be in [0, 4.5] m")
        known = ("braking", "aeb3m", "oracle")
        if any(p not in known for p in self.policies):
            yield ConfigValueError("policies", list(self.policies), f"use some of {', '.join(known)}")
        half = CAR_LENGTH / 2
        if not abs(self.impact_offset) <= half:
            yield ConfigValueError("kim.impact_offset", self.impact_offset, f"it must be within ±{half:g} m")
