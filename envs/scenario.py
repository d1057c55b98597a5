"""Imminent-collision scenarios: the paper's distributions (section IV-A), validation and the test bank.

A scenario is a plain, frozen dataclass. Everything random about an episode that is not in its fields
(hazard side and angle, traffic and pedestrian placement, the static layout) is drawn from ``seed``, so
``env.reset(options={"scenario": spec})`` replays an episode exactly.

The hazard geometry is defined so that, at constant ego speed (action [0, 0]), first contact happens at
exactly t = TTC: the hazard pedestrian's centre, or the near side of the hazard car, is at the point the
ego's front bumper reaches at TTC.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, fields

import numpy as np

# The paper's sampling ranges (Porav & Newman 2018, section IV-A).
TTC_RANGE = (0.25, 1.5)
EGO_SPEED_RANGE = (1.0, 30.0)
PEDESTRIAN_SPEED_RANGE = (1.0, 5.0)
MAX_OTHERS = 10
# Not given by the paper: a car emerging from a side street at urban junction speeds.
HAZARD_CAR_SPEED_RANGE = (4.0, 12.0)

# What a spec may hold (wider than the sampling ranges so that stress tests can go beyond them).
_LIMITS = {
    "ttc": (0.0, 10.0),
    "ego_speed": (0.0, 40.0),
    "pedestrian_speed": (0.0, 10.0),
    "hazard_car_speed": (0.0, 30.0),
}


def _whole(value) -> bool:
    """A finite whole number (int() of inf or nan would raise before the field could be named)."""
    return math.isfinite(value) and int(value) == value


@dataclass(frozen=True)
class ScenarioSpec:
    """One imminent-collision scenario.

    ttc: time to collision at constant ego speed (s). ego_speed: the collision speed v_c (m/s).
    pedestrian_speed: v_p of the hazard pedestrian (m/s). n_cars, n_pedestrians: other traffic.
    p_pedestrian, p_car: the paper's infraction draws; a hazard of that kind exists when > 0.5.
    hazard_car_speed: speed of the crossing car (m/s). seed: everything else about the episode.
    """

    seed: int
    ttc: float
    ego_speed: float
    pedestrian_speed: float = 2.0
    n_cars: int = 0
    n_pedestrians: int = 0
    p_pedestrian: float = 0.0
    p_car: float = 0.0
    hazard_car_speed: float = 8.0

    def __post_init__(self):
        for name, (lo, hi) in _LIMITS.items():
            value = getattr(self, name)
            if not (lo < value <= hi) or value != value:
                raise ValueError(f"scenario field {name}={value!r} is out of range: it must be in ({lo}, {hi}]")
        for name in ("n_cars", "n_pedestrians"):
            value = getattr(self, name)
            if not _whole(value) or not 0 <= value <= MAX_OTHERS:
                raise ValueError(
                    f"scenario field {name}={value!r} is out of range: it must be an integer in 0..{MAX_OTHERS}"
                )
        for name in ("p_pedestrian", "p_car"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"scenario field {name}={value!r} is out of range: it must be in [0, 1]")
        if not _whole(self.seed) or self.seed < 0:
            raise ValueError(f"scenario field seed={self.seed!r} must be a non-negative integer")

    @property
    def pedestrian_hazard(self) -> bool:
        return self.p_pedestrian > 0.5

    @property
    def car_hazard(self) -> bool:
        return self.p_car > 0.5

    @property
    def hazard(self) -> str:
        """'pedestrian', 'car', 'both' or 'none'."""
        if self.pedestrian_hazard and self.car_hazard:
            return "both"
        if self.pedestrian_hazard:
            return "pedestrian"
        return "car" if self.car_hazard else "none"

    def to_dict(self) -> dict:
        return asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict) -> ScenarioSpec:
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown scenario fields: {sorted(unknown)}")
        return cls(**d)


def sample_scenario(rng: np.random.Generator) -> ScenarioSpec:
    """Draw a scenario from the paper's distributions."""
    return ScenarioSpec(
        seed=int(rng.integers(0, 2**31 - 1)),
        ttc=float(rng.uniform(*TTC_RANGE)),
        ego_speed=float(rng.uniform(*EGO_SPEED_RANGE)),
        pedestrian_speed=float(rng.uniform(*PEDESTRIAN_SPEED_RANGE)),
        n_cars=int(rng.integers(0, MAX_OTHERS + 1)),
        n_pedestrians=int(rng.integers(0, MAX_OTHERS + 1)),
        p_pedestrian=float(rng.uniform(0.0, 1.0)),
        p_car=float(rng.uniform(0.0, 1.0)),
        hazard_car_speed=float(rng.uniform(*HAZARD_CAR_SPEED_RANGE)),
    )


def sample_focus_scenario(
    rng: np.random.Generator,
    hazard_share: float = 0.85,
    speed_range: tuple[float, float] = (15.0, 30.0),
    ttc_range: tuple[float, float] = (0.25, 1.1),
) -> ScenarioSpec:
    """Draw from the focus mix: the cells where braking leaves injuries a better manoeuvre avoids.

    With probability ``hazard_share`` a pedestrian, a car or both (one third each, as in the bank) meet the ego;
    otherwise there is no hazard, so a policy trained on the mix also sees that swerving there only costs. Speed
    and TTC are uniform in their ranges; the other fields follow the paper's distributions.
    """
    if not 0.0 <= hazard_share <= 1.0:
        raise ValueError(f"focus hazard_share={hazard_share} must be in [0, 1]")
    for name, (lo, hi) in (("speed_range", speed_range), ("ttc_range", ttc_range)):
        if not 0 < lo <= hi:
            raise ValueError(f"focus {name}=({lo}, {hi}) must satisfy 0 < low <= high")
    seed = int(rng.integers(0, 2**31 - 1))
    hazard = BANK_HAZARDS[int(rng.integers(0, 3))] if rng.uniform() < hazard_share else "none"
    ttc, speed = float(rng.uniform(*ttc_range)), float(rng.uniform(*speed_range))
    return hazard_scenario(rng, seed, hazard, ttc, speed)


def hazard_scenario(rng: np.random.Generator, seed: int, hazard: str, ttc: float, speed: float) -> ScenarioSpec:
    """A scenario with the given hazard ('pedestrian', 'car', 'both' or 'none'), TTC and speed; pedestrian speed,
    traffic and the crossing car's speed drawn from ``rng`` (in that order) from the paper's ranges."""
    return ScenarioSpec(
        seed=seed,
        ttc=float(ttc),
        ego_speed=float(speed),
        pedestrian_speed=float(rng.uniform(*PEDESTRIAN_SPEED_RANGE)),
        n_cars=int(rng.integers(0, MAX_OTHERS + 1)),
        n_pedestrians=int(rng.integers(0, MAX_OTHERS + 1)),
        p_pedestrian=1.0 if hazard in ("pedestrian", "both") else 0.0,
        p_car=1.0 if hazard in ("car", "both") else 0.0,
        hazard_car_speed=float(rng.uniform(*HAZARD_CAR_SPEED_RANGE)),
    )


# ----------------------------------------------------------------------------- scenario banks
BANK_TTCS = (0.5, 0.75, 0.9, 1.0, 1.1, 1.3, 1.5)
BANK_SPEEDS = (10.0, 20.0, 30.0)
BANK_HAZARDS = ("pedestrian", "car", "both")


@dataclass(frozen=True)
class BankEntry:
    scenario_id: int
    hazard: str
    ttc: float
    speed: float
    index: int  # position within its cell
    spec: ScenarioSpec


def scenario_bank(
    ttcs=BANK_TTCS, speeds=BANK_SPEEDS, hazards=BANK_HAZARDS, per_cell: int = 20, *, seed: int
) -> list[BankEntry]:
    """A seeded evaluation bank (docs/design.md §6): a validation bank or the sealed test bank, by ``seed``
    (worldmodel/banks.py declares which seed is which).

    A scenario's free parameters depend only on (seed, hazard, TTC, speed, index), not on which other cells
    are requested, so a smaller bank is a subset of a larger one and every policy sees the same scenarios.
    """
    if per_cell < 1:
        raise ValueError(f"per_cell={per_cell} must be at least 1")
    entries = []
    for hazard in hazards:
        if hazard not in BANK_HAZARDS:
            raise ValueError(f"hazard={hazard!r} must be one of {BANK_HAZARDS}")
        for ttc in ttcs:
            for speed in speeds:
                for i in range(per_cell):
                    key = [seed, BANK_HAZARDS.index(hazard), int(round(ttc * 1000)), int(round(speed * 1000)), i]
                    rng = np.random.default_rng(key)
                    spec = hazard_scenario(rng, int(rng.integers(0, 2**31 - 1)), hazard, ttc, speed)
                    entries.append(BankEntry(len(entries), hazard, float(ttc), float(speed), i, spec))
    return entries
