"""Scenario family ``merola``: Merola et al. 2022, three pre-accident scenarios on the street (docs/design.md §10).

The ego drives along its lane (towards +x) at U(30, 60) km/h, and one other car, also at U(30, 60) km/h, makes the
crash imminent:

* ``lead_brake``: a lead car in the ego's lane, a time headway of U(1, 2) s ahead (bumper to bumper, at the ego's
  speed), brakes at U(6, 9.8) m/s² to a stop from the first instant;
* ``crossing``: a car comes out of the side street, from the left or the right, at speed across the junction: at
  constant speeds its centre would cross the ego's lane centre when the ego's front bumper reaches its near flank,
  U(1.0, 2.5) s after the start (the scenario's TTC);
* ``drift``: an oncoming car loses control and drifts into the ego's lane at U(2, 4) m/s sideways, starting when the
  time to collision (front-to-front gap over the closing speed) has fallen to U(1.5, 3.0) s, one second after the
  start; it drifts until its centre is on the ego's lane centre, then runs on straight.

Episodes are 60 steps of 0.1 s (``env.step_s`` = 0.1, which ``conf/agent/ddqn_merola.yaml`` sets) and end at the
first crash. The paper spawns its scenarios at 5 points, 3 on straight road and 2 at an intersection; ours puts the
street's junction in view (15-50 m ahead, or at the crossing car's path) in every ``crossing`` episode and in
``AT_JUNCTION_P`` of the others, so that the junction is in view in 40 % of all episodes, our default (docs/design.md
§10). The street (buildings, poles, parked furniture) is the one the camera draws, so the family runs with the camera
on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .actors import Actors
from .scene import EGO_LANE_Y, JUNCTION_HALF_WIDTH, ONCOMING_LANE_Y, StaticLayout, sample_layout
from .specs import FamilySpec
from .streams import MEROLA_JUNCTION_DISTANCE

FAMILY = "merola"
SCENARIOS = ("lead_brake", "crossing", "drift")
SPEED_RANGE = (30.0 / 3.6, 60.0 / 3.6)
HEADWAY_RANGE = (1.0, 2.0)
LEAD_DECEL_RANGE = (6.0, 9.8)
CROSSING_TTC_RANGE = (1.0, 2.5)
DRIFT_TTC_RANGE = (1.5, 3.0)
DRIFT_SPEED_RANGE = (2.0, 4.0)
DRIFT_AFTER_S = 1.0  # the drift starts this long after the episode's start
EPISODE_STEPS, STEP_S = 60, 0.1
AT_JUNCTION_P = 0.1  # lead_brake and drift at the junction: 1/3 + 2/3 * 0.1 = 40 % of episodes in view of one
JUNCTION_AHEAD_M = (15.0, 50.0)
SIDE_LANE_M = 1.75  # the crossing car drives on its right-hand half of the side street
CAR_LENGTH, CAR_WIDTH = 4.5, 1.8  # every car's footprint is the ego's (envs/vehicle.py)
ENDS: tuple[str, ...] = ()  # only crashes and the 6 s horizon end an episode
_LIMITS = {"ego_speed": (0.0, 40.0), "other_speed": (0.0, 40.0), "ttc": (0.0, 10.0)}


@dataclass(frozen=True)
class MerolaSpec(FamilySpec):
    """One Merola scenario. scenario: lead_brake, crossing or drift; ego_speed and other_speed (m/s); ttc (s): the
    lead's time headway, the crossing car's TTC or the drift's TTC at its start; lead_decel (m/s², lead_brake);
    drift_speed (m/s, drift); from_left: the crossing car comes from the ego's left; at_junction: the street's
    junction is in view (always for crossing); seed: the street layout and the junction's distance."""

    seed: int
    scenario: str
    ego_speed: float
    other_speed: float
    ttc: float
    lead_decel: float = 8.0
    drift_speed: float = 3.0
    from_left: bool = False
    at_junction: bool = False
    family: str = FAMILY

    def __post_init__(self):
        if self.family != FAMILY:
            raise ValueError(f"scenario field family={self.family!r}: a MerolaSpec is family {FAMILY!r}")
        if self.scenario not in SCENARIOS:
            raise ValueError(f"scenario field scenario={self.scenario!r}: use one of {', '.join(SCENARIOS)}")
        for name, (lo, hi) in _LIMITS.items():
            value = getattr(self, name)
            if not lo < value <= hi or value != value:
                raise ValueError(f"scenario field {name}={value!r} is out of range: it must be in ({lo}, {hi}]")
        if not 0.0 < self.lead_decel <= 15.0:
            raise ValueError(f"scenario field lead_decel={self.lead_decel!r} is out of range: it must be in (0, 15]")
        if not 0.0 < self.drift_speed <= 10.0:
            raise ValueError(f"scenario field drift_speed={self.drift_speed!r} is out of range: it must be in (0, 10]")
        for name in ("from_left", "at_junction"):
            if not isinstance(getattr(self, name), bool | np.bool_):
                raise ValueError(f"scenario field {name}={getattr(self, name)!r} must be true or false")
        if int(self.seed) != self.seed or self.seed < 0:
            raise ValueError(f"scenario field seed={self.seed!r} must be a non-negative integer")

    @property
    def hazard(self) -> str:
        return "car"


SPEC = MerolaSpec


def sample(rng: np.random.Generator, scenario: str | None = None) -> MerolaSpec:
    """The training distribution: the three scenarios equally likely (or ``scenario``), the rest as
    docs/design.md §10 says."""
    name = str(SCENARIOS[int(rng.integers(len(SCENARIOS)))]) if scenario is None else scenario
    ttc_range = {"lead_brake": HEADWAY_RANGE, "crossing": CROSSING_TTC_RANGE, "drift": DRIFT_TTC_RANGE}[name]
    return MerolaSpec(
        seed=int(rng.integers(0, 2**31 - 1)),
        scenario=name,
        ego_speed=float(rng.uniform(*SPEED_RANGE)),
        other_speed=float(rng.uniform(*SPEED_RANGE)),
        ttc=float(rng.uniform(*ttc_range)),
        lead_decel=float(rng.uniform(*LEAD_DECEL_RANGE)),
        drift_speed=float(rng.uniform(*DRIFT_SPEED_RANGE)),
        from_left=bool(rng.random() < 0.5),
        at_junction=name == "crossing" or bool(rng.random() < AT_JUNCTION_P),
    )


# ----------------------------------------------------------------------------- the other car's motion
@dataclass(frozen=True)
class Motion:
    """The other car's pose over time, in closed form: from (x0, y0) along ``heading`` at ``speed``, braking at
    ``decel`` from t = 0 to a stop (0: none), and from ``drift_t`` on moving sideways at ``drift_vy`` (m/s, signed)
    until it has moved ``drift_dy`` (m); while it drifts it points along its velocity."""

    x0: float
    y0: float
    heading: float
    speed: float
    decel: float = 0.0
    drift_t: float = math.inf
    drift_vy: float = 0.0
    drift_dy: float = 0.0

    def pose(self, t: float) -> tuple[float, float, float]:
        if self.decel > 0.0:
            tb = min(t, self.speed / self.decel)
            s = self.speed * tb - 0.5 * self.decel * tb * tb
        else:
            s = self.speed * t
        x, y = self.x0 + s * math.cos(self.heading), self.y0 + s * math.sin(self.heading)
        h = self.heading
        if t > self.drift_t and self.drift_vy != 0.0:
            lateral_s = abs(self.drift_dy / self.drift_vy)
            y += self.drift_vy * min(t - self.drift_t, lateral_s)
            if t - self.drift_t < lateral_s:
                h = math.atan2(self.drift_vy, self.speed * math.cos(self.heading))
        return x, y, h


@dataclass
class MerolaState:
    """The other car's motion and the junction; hooks as in ``envs.chae.ChaeState``."""

    motion: Motion
    junction_x: float
    horizon_s: float = EPISODE_STEPS * STEP_S

    def substep(self, actors: Actors, bumper_before: float, bumper_after: float, t0: float, tau: float, sub_dt: float):
        """Move the car to its pose at t0 + tau: the env places cars at ``xy + vel * tau`` within a step, so the
        velocity is set to reach that point exactly (and ``advance`` lands on it)."""
        x, y, h = self.motion.pose(t0 + tau)
        actors.car_vel[0] = ((x - actors.car_xy[0, 0]) / tau, (y - actors.car_xy[0, 1]) / tau)
        actors.car_heading[0] = h

    def context(self, actors: Actors, bumper_x: float, ego=None) -> dict:
        return {}

    def end(self, actors: Actors, bumper_x: float, speed: float, ctx: dict, ego=None) -> str | None:
        return None

    def outcome(self, spec: MerolaSpec, bumper_x: float) -> dict:
        return {"family": FAMILY, "scenario": spec.scenario, "at_junction": int(spec.at_junction)}


def motion(spec: MerolaSpec, ego_front: float) -> tuple[Motion, float | None]:
    """The other car's motion for ``spec`` with the ego's front bumper at ``ego_front`` at t = 0, and the junction's
    x when the scenario fixes it (crossing), else None."""
    v, u = spec.ego_speed, spec.other_speed
    if spec.scenario == "lead_brake":
        centre = ego_front + v * spec.ttc + CAR_LENGTH / 2
        return Motion(centre, EGO_LANE_Y, 0.0, u, decel=spec.lead_decel), None
    if spec.scenario == "crossing":
        path_x = ego_front + v * spec.ttc + CAR_WIDTH / 2  # the ego's bumper meets its near flank at TTC
        direction = -1.0 if spec.from_left else 1.0  # from the right it drives towards +y
        start_y = EGO_LANE_Y - direction * u * spec.ttc
        junction_x = path_x - direction * SIDE_LANE_M  # it keeps to the right-hand half of the side street
        return Motion(path_x, start_y, direction * math.pi / 2, u), junction_x
    # drift: the fronts' gap closes at v + u; the drift starts DRIFT_AFTER_S in, at TTC spec.ttc
    gap = (v + u) * (spec.ttc + DRIFT_AFTER_S)
    centre = ego_front + gap + CAR_LENGTH / 2
    dy = EGO_LANE_Y - ONCOMING_LANE_Y
    return Motion(centre, ONCOMING_LANE_Y, math.pi, u, 0.0, DRIFT_AFTER_S, -spec.drift_speed, dy), None


def build(spec: MerolaSpec, ego_front: float) -> tuple[Actors, MerolaState]:
    move, junction_x = motion(spec, ego_front)
    rng = np.random.default_rng([spec.seed, MEROLA_JUNCTION_DISTANCE])
    if junction_x is None:
        ahead = rng.uniform(*JUNCTION_AHEAD_M) if spec.at_junction else rng.uniform(200.0, 300.0)
        junction_x = ego_front + float(ahead)
    actors = Actors.empty(collision_point=None)
    x, y, h = move.pose(0.0)
    actors.car_xy[0] = (x, y)
    actors.car_heading[0] = h
    actors.car_active[0] = actors.car_hazard[0] = True
    return actors, MerolaState(move, float(junction_x))


def layout(spec: MerolaSpec, state: MerolaState, rng: np.random.Generator) -> StaticLayout:
    """The street, drawn from the spec's seed around the scenario's junction (kept clear of the side street)."""
    return sample_layout(rng, state.junction_x)


assert JUNCTION_HALF_WIDTH > SIDE_LANE_M + CAR_WIDTH / 2  # the crossing car fits on its half of the side street


# ----------------------------------------------------------------------------- scripted policies, against the reward
class Hold:
    """Drives on: no pedal, the wheel straight. What Merola's reward pays for metres covered and a crash's clipped
    penalty, with no stop to pay for."""

    name = "hold"

    def reset(self, seed: int | None = None) -> None:
        pass

    def act(self, obs, info) -> np.ndarray:
        return np.array([0.0, 0.0], dtype=np.float32)


class BrakeThenRelease:
    """Straight-line braking that lets go of the brake below Merola's v_min (``envs.rewards.MEROLA_V_MIN``, 2 m/s),
    where the reward charges every step of braking: never charged, it rolls on at just under v_min."""

    name = "brake_release"

    def reset(self, seed: int | None = None) -> None:
        pass

    def bind(self, env) -> None:
        self.env = env

    def release_below(self) -> float:
        from .rewards import MEROLA_V_MIN

        return MEROLA_V_MIN

    def act(self, obs, info) -> np.ndarray:
        braking = self.env.ego.v >= self.release_below() and self.env.ego.v > 0.0
        return np.array([0.0, -1.0 if braking else 0.0], dtype=np.float32)


class BrakeToStandstill(BrakeThenRelease):
    """Straight-line braking to a standstill, then no pedal: charged for the few steps of braking below v_min, it
    then stands still for nothing."""

    name = "brake_stop"

    def release_below(self) -> float:
        return 0.0
