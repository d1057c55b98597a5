"""The reward registry: every reward the simulator knows, in one place (docs/design.md §3).

A reward is a function of one step: the collisions registered in it, the ego's state before and after, the action,
and what the scenario's family adds (``StepContext.family``: e.g. the distance to a crossing pedestrian). The env
computes every registered reward on every step, reports each in ``info["reward_<name>"]`` and its sum in
``outcome["return_<name>"]``, and hands the one its ``reward=`` setting names to the learner. A new reward is one
decorated function here; configs, the env's checks and the agents' run names read :data:`REWARDS`.

R1 and R2 are Porav & Newman 2018's Eq. 7 and 8, given on the step a collision happens: R1 = -(n_ped + n_occ)
counts the people involved; R2 = -(sum P_ped + sum P_occ) weights them by the empirical injury risks of
``envs.injury``. Otherwise they are 0, exactly as in the paper.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .chae import reward as chae_reward
from .injury import injury_severity_score


@dataclass(frozen=True)
class StepContext:
    """What a reward may read about one step. Speeds in m/s, ``step_s`` in s; ``action`` = [steer, pedal]."""

    hits: list[dict]
    speed_before: float
    speed_after: float
    action: np.ndarray
    step_s: float
    family: dict = field(default_factory=dict)
    heading: float = 0.0  # the ego's heading after the step, rad, counter-clockwise from the road's direction


@dataclass(frozen=True)
class Reward:
    name: str
    fn: Callable[[StepContext], float]
    doc: str


REGISTRY: dict[str, Reward] = {}
REWARDS: tuple[str, ...] = ()  # the registered rewards' names, in order


def register(name: str, doc: str) -> Callable:
    """Add ``fn(ctx: StepContext) -> float`` to the registry under ``name``."""

    def add(fn: Callable[[StepContext], float]) -> Callable[[StepContext], float]:
        global REWARDS
        if name in REGISTRY:
            raise ValueError(f"reward {name!r} is registered twice")
        REGISTRY[name] = Reward(name, fn, doc)
        REWARDS = tuple(REGISTRY)
        return fn

    return add


def unregister(name: str) -> None:
    """Remove reward ``name`` (a test's own reward, once the test is done)."""
    global REWARDS
    REGISTRY.pop(name, None)
    REWARDS = tuple(REGISTRY)


@register("r1", "Porav & Newman Eq. 7: minus the number of people involved in this step's collisions")
def r1(ctx: StepContext) -> float:
    return -float(sum(c["n_involved"] for c in ctx.hits))


@register("r2", "Porav & Newman Eq. 8: minus the summed injury probabilities of this step's collisions")
def r2(ctx: StepContext) -> float:
    return -float(sum(c["injury_sum"] for c in ctx.hits))


@register("chae", "Chae et al. 2017 Eq. 8: braking costs more the farther the pedestrian; a bump costs 100 + 0.01 v^2")
def chae(ctx: StepContext) -> float:
    return chae_reward(ctx)


def crash_iss(hits: list[dict], units: str = "kmh") -> float:
    """The summed Sobhani ISS of the ego's occupant over these crashes with cars and obstacles (Kim et al. Eq. 11;
    ΔV in ``units``, envs/injury.py). Pedestrian contacts do not count: they barely change the ego's velocity."""
    crashes = [h for h in hits if h["kind"] != "pedestrian"]
    return float(sum(injury_severity_score(h["delta_v_ego"], h["ego_side"], units=units) for h in crashes))


@register("kim_unaware", "Kim et al. 2020 Eq. 9: minus the Sobhani ISS of this step's crashes (ΔV in km/h), else 0")
def kim_unaware(ctx: StepContext) -> float:
    return -crash_iss(ctx.hits)


@register("kim_aware", "Kim et al. 2020 Eq. 10: the progress to the goal (d_{t-1} - d_t) without a crash, else -ISS")
def kim_aware(ctx: StepContext) -> float:
    if any(h["kind"] != "pedestrian" for h in ctx.hits):
        return -crash_iss(ctx.hits)
    return float(ctx.family.get("goal_progress", 0.0))


# Merola et al. 2022 §3.1 and §4, with our defaults where the paper gives no number (docs/design.md §10)
MEROLA_V_MIN, MEROLA_V_MAX, MEROLA_PHI_MAX = 2.0, 60.0 / 3.6, math.radians(10.0)
MEROLA_IMPACT_FULL_MS = 60.0 / 3.6  # a crash at this ego delta-v (pedestrian: impact speed) costs the full 100


def merola_impact(hits: list[dict]) -> float:
    """Merola's collision penalty of this step's crashes: each clip(100 dv / 16.67 m/s, 1, 100), with dv the ego's
    velocity change (a pedestrian: the impact speed)."""
    total = 0.0
    for h in hits:
        dv = h["impact_speed"] if h["kind"] == "pedestrian" else h["delta_v_ego"]
        total += min(100.0, max(1.0, 100.0 * float(dv) / MEROLA_IMPACT_FULL_MS))
    return total


@register(
    "merola",
    "Merola et al. 2022: -impact (1..100), +1 per metre, -5 for braking below v_min or throttle above v_max, "
    "-1 for steering further off the road's direction beyond 10 deg",
)
def merola(ctx: StepContext) -> float:
    pedal, steer = float(ctx.action[1]), float(ctx.action[0])
    r = 0.5 * (ctx.speed_before + ctx.speed_after) * ctx.step_s - merola_impact(ctx.hits)
    if pedal < 0.0 and ctx.speed_after < MEROLA_V_MIN:
        r -= 5.0
    if pedal > 0.0 and ctx.speed_after > MEROLA_V_MAX:
        r -= 5.0
    # a positive steer turns right, lowering the heading: steering further off is -steer with the heading's sign
    if abs(ctx.heading) > MEROLA_PHI_MAX and -steer * ctx.heading > 0.0:
        r -= 1.0
    return r


MEROLA_MOST_PROGRESS = 100.0  # m: the most an episode pays for progress (6 s at the 60 km/h top of the range)


@register(
    "merola_safe",
    "Merola's reward, each crash costing a further 100 (the most progress an episode pays): a deviation, so that no "
    "crash outranks a stop (docs/results/merola/reward/)",
)
def merola_safe(ctx: StepContext) -> float:
    return merola(ctx) - MEROLA_MOST_PROGRESS * len(ctx.hits)


def step_rewards(ctx: StepContext) -> dict[str, float]:
    """Every registered reward of one step, by name."""
    return {name: float(r.fn(ctx)) for name, r in REGISTRY.items()}


def collision_rewards(collisions: list[dict]) -> tuple[float, float]:
    """(R1, R2) of the collisions registered in one step."""
    ctx = StepContext(collisions, 0.0, 0.0, np.zeros(2), 0.0)
    return r1(ctx), r2(ctx)
