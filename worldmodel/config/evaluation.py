"""The evaluation sections: the privileged planner, the scripted policies, the paper's bank and the Euro NCAP bank.
Each family's own evaluation keys (``evaluate.<section>``) are declared by the family
(worldmodel/families/<name>/config.py) and joined from the registry (``family_sections``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from .. import registry
from ..banks import seed_problems
from ..common import Checked, ConfigValueError, worker_count_problems
from ..common import positive_fields as _positive
from .family_sections import with_family_sections


@dataclass
class OracleConfig(Checked):
    """The privileged planner (``envs/planner.py``): the ceiling the agents are judged against."""

    replan_every_s: float = 0.2  # re-simulate the candidates from the true state this often
    pedals: list[float] = field(default_factory=lambda: [-1.0, -0.5, 0.0, 1.0])  # held pedal levels; must hold -1
    steers: list[float] = field(default_factory=lambda: [0.3, 0.6, 1.0])  # steering magnitudes, both ways
    delays_s: list[float] = field(default_factory=lambda: [0.0, 0.2, 0.4])  # when the steering starts
    lane_change_s: list[float] = field(default_factory=lambda: [0.3, 0.6])  # steer-then-counter-steer lengths
    # steering directions tried, in order: 1 right, -1 left (one side: a teacher without left/right ambiguity)
    sides: list[float] = field(default_factory=lambda: [1.0, -1.0])
    # frames of straight-line braking before planning starts: the perception ceiling (a camera policy that needs
    # this many frames to see the hazard); 0 for the ceiling itself
    brake_first: int = 0

    def problems(self):
        from envs.planner import candidate_manoeuvres

        if self.replan_every_s <= 0:
            yield ConfigValueError("oracle.replan_every_s", self.replan_every_s, "it must be > 0")
        if self.brake_first < 0:
            yield ConfigValueError("oracle.brake_first", self.brake_first, "it must be >= 0 frames")
        try:
            candidate_manoeuvres(
                pedals=list(self.pedals),
                steers=list(self.steers),
                delays_s=list(self.delays_s),
                lane_change_s=list(self.lane_change_s),
                sides=list(self.sides),
            )
        except ValueError as err:
            yield ConfigValueError("oracle", "...", str(err))


# braking (the floor), the privileged planner (the ceiling), and the planner after braking straight for its first 1
# or 2 frames: the perception ceilings of a camera policy that needs that many frames to see the hazard; and the
# planner braking straight until the hazard covers 1 or 3 pixels of the camera frame: the camera's cap
SCRIPTED_POLICIES = ("braking", "oracle", "oracle_brake1", "oracle_brake2", "oracle_pixels1", "oracle_pixels3")


@dataclass
class EvaluateSettings(Checked):
    """The seeded scenario banks (docs/design.md §6) and the scripted policies evaluated beside the agents;
    ``EvaluateConfig`` below adds each family's own section (``evaluate.<section>``)."""

    per_cell: int = 5
    ttcs: list[float] = field(default_factory=lambda: [0.5, 0.75, 0.9, 1.0, 1.1, 1.3, 1.5])
    speeds: list[float] = field(default_factory=lambda: [10.0, 20.0, 30.0])
    hazards: list[str] = field(default_factory=lambda: ["pedestrian", "car", "both"])
    # which bank (worldmodel/banks.py): "validation", drawn from validation_seed, for choosing settings and
    # checkpoints, as often as needed; "test", the sealed test bank, for final numbers only: each evaluation on it
    # is recorded in the ledger (paths.ledger) and goes to runs/NAME/eval_test/
    bank: str = "validation"
    # true: evaluate on a test bank that the ledger already records for this experiment and family, adding a second
    # row; for a configuration changed after its test result (the first row stays). False: such a run is refused
    retest: bool = False
    validation_seed: int = 4711  # the default validation bank (runs/NAME/eval/); others go to eval_seed<N>/
    # processes; auto: the cores this process may use. Results are identical for any count (tested)
    num_workers: int | str = "auto"
    # scripted policies; every agent under runs/${experiment}/agent_*/seed*/ is added
    policies: list[str] = field(default_factory=lambda: ["braking", "oracle"])
    oracle: OracleConfig = field(default_factory=OracleConfig)
    # which scenario family to evaluate: the paper's (the registry's default; the bank above) or another registered
    # family, on its own section (evaluate.<section>)
    family: str = registry.default().name

    UNHASHED = ("num_workers", "retest")  # rows are identical for any worker count (tested); a permission

    @classmethod
    def as_recorded(cls, values: dict, settings: dict) -> None:
        """Only the evaluated family's own section shapes an evaluation; the paper's bank hashes as before the
        families existed (no family, no sections)."""
        family = registry.family(values.get("family") or registry.default().name)
        for section in registry.sections():
            if section != family.section or family is registry.default():
                values.pop(section, None)
        if family is registry.default():
            values.pop("family", None)
        super().as_recorded(values, settings)

    def problems(self):
        yield from _positive(self, "per_cell")
        yield from worker_count_problems(self, "num_workers")
        for key in ("ttcs", "speeds", "hazards"):
            if not getattr(self, key):
                yield ConfigValueError(key, [], "it must not be empty")
        for key in ("ttcs", "speeds"):
            if any(v <= 0 for v in getattr(self, key)):
                yield ConfigValueError(key, list(getattr(self, key)), "every value must be positive")
        from ..banks import BANKS

        if self.bank not in BANKS:
            yield ConfigValueError("bank", self.bank, f"it must be one of {', '.join(BANKS)}")
        from envs.families import names

        known = names()
        if self.family not in known:
            yield ConfigValueError("family", self.family, f"it must be one of {', '.join(known)}")
        yield from seed_problems(self, "validation_seed")
        unknown = [h for h in self.hazards if h not in ("pedestrian", "car", "both")]
        if unknown:
            yield ConfigValueError("hazards", list(self.hazards), "hazards are pedestrian, car and both")
        if "braking" not in self.policies or any(p not in SCRIPTED_POLICIES for p in self.policies):
            yield ConfigValueError(
                "policies",
                list(self.policies),
                "it must include 'braking' (the baseline) and may add "
                f"{', '.join(repr(p) for p in SCRIPTED_POLICIES[1:])}; trained agents are found by themselves",
            )


EvaluateConfig = with_family_sections(EvaluateSettings, "eval_config", "EvaluateConfig")


@dataclass
class NcapConfig(Checked):
    """The Euro NCAP bank (worldmodel/ncap.py): the pedestrian tests and the car-to-car rear tests."""

    # the paper's agents (and braking, the planner) act from this TTC on; before it the car holds its speed
    takeover_ttc_s: float = 1.5
    tests: list[str] = field(default_factory=lambda: ["CPFA-50", "CPNA-25", "CPNA-75", "CPNC-50"])
    speeds_kmh: list[float] = field(default_factory=lambda: [float(v) for v in range(20, 65, 5)])
    # car-to-car: CCRs and CCRm at every car_speed_step_kmh of their speed range and every overlap; CCRb's 4 variants
    car_tests: list[str] = field(default_factory=lambda: ["CCRs", "CCRm", "CCRb"])
    overlaps_pct: list[float] = field(default_factory=lambda: [-75.0, -50.0, 50.0, 75.0, 100.0])
    car_speed_step_kmh: float = 5.0

    def problems(self):
        from envs.ncap import CAR_TESTS, TESTS

        if any(t not in TESTS for t in self.tests):
            yield ConfigValueError("tests", list(self.tests), f"use a list of {', '.join(TESTS)}")
        if any(t not in CAR_TESTS for t in self.car_tests):
            yield ConfigValueError("car_tests", list(self.car_tests), f"use a list of {', '.join(CAR_TESTS)}")
        if not self.tests and not self.car_tests:
            yield ConfigValueError("tests", [], "give at least one pedestrian or car-to-car test")
        if any(not 0 < abs(o) <= 100 for o in self.overlaps_pct) or not self.overlaps_pct:
            yield ConfigValueError("overlaps_pct", list(self.overlaps_pct), "use overlaps in [-100, 0) or (0, 100]")
        if self.car_speed_step_kmh <= 0 or self.car_speed_step_kmh % 5:
            yield ConfigValueError("car_speed_step_kmh", self.car_speed_step_kmh, "use a positive multiple of 5")
        if not self.speeds_kmh or any(not 0 < v <= 150 for v in self.speeds_kmh):
            yield ConfigValueError("speeds_kmh", list(self.speeds_kmh), "use speeds in (0, 150] km/h")
        if not 0.0 < self.takeover_ttc_s <= 4.0:
            yield ConfigValueError(
                "takeover_ttc_s", self.takeover_ttc_s, "it must be in (0, 4] s (the tests start at 4 s)"
            )
