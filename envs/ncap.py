"""Scenario family ``ncap``: the Euro NCAP AEB pedestrian and car-to-car tests, as one fixed bank for every policy.

| test | pedestrian | walks from | impact point on the car's front |
|---|---|---|---|
| CPFA-50 | adult, 8 km/h | the far side | 50 % of the car's width |
| CPNA-25 / -75 | adult, 5 km/h | the near side (the kerb of the ego's lane) | 25 % / 75 % of the width |
| CPNC-50 | child, 5 km/h, hidden behind two parked cars | the near side | 50 % |

The car drives straight at the test speed (20-60 km/h in 5 km/h steps); the pedestrian starts at rest and would
reach the impact point, measured across the car's width from the side it comes from, exactly when the front bumper
does at constant car speed, 4 s after the start (TTC 4 s). The episode ends on contact with the pedestrian
(``impact``), when the car stands still (``stop``) or when its front bumper has passed the pedestrian's path
(``pass``); at the latest 7 s after the start.

Our choices where the protocol is not at hand (docs/design.md §10 lists them as unverified; every result is labelled
approximate): the pedestrian accelerates over its first 1 m; we model that as standing still for 1/v_p s and then
walking at v_p, which reaches the impact point at the same instant (positions differ by at most 0.25 m, while the
pedestrian is still outside the carriageway). Our pedestrian has one body size, so the child is an adult-sized
footprint; CPNC-50's two parked 4.5 x 1.8 m cars stand at the kerb, just upstream of the child's path, 1 m apart,
clear of a car that keeps its lane. The street's static layout (poles, walls) is drawn from the spec's seed as
elsewhere.

Car-to-car rear tests (``CAR_TESTS``): a target car ahead in the ego's lane, offset sideways so that the two cars'
fronts overlap by ``overlap_pct`` of the width (positive: the target is offset to the ego's right, the kerb side;
our choice, the sources at hand do not say):

| test | target | test-car speeds | variants |
|---|---|---|---|
| CCRs | stationary | 10-50 km/h | overlap -75, -50, +50, +75, 100 % |
| CCRm | 20 km/h | 30-80 km/h | the same overlaps |
| CCRb | 50 km/h, braking at 2 or 6 m/s² from the start | 50 km/h | gap 12 or 40 m, 100 % |

CCRs and CCRm start at TTC 4 s (bumper gap = closing speed × 4 s); CCRb starts as the target begins to brake. A
run ends when the cars touch (``crash``), when the test car stands still (``stop``) or becomes slower than the
target (``slower``); at the latest 7 s after the start. Points per impact-speed band (``car_points``) are confirmed
only for CCRs at 50 km/h and for full avoidance at 20 km/h and below; elsewhere the same bands are
applied and labelled approximate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .actors import Actors
from .merola import Motion
from .scene import EGO_LANE_Y, ROAD_HALF_WIDTH
from .specs import FamilySpec

FAMILY = "ncap"
# test -> (starts on the far side, walking speed km/h, impact point as a share of the car's width, parked cars)
TESTS = {
    "CPFA-50": (True, 8.0, 0.50, False),
    "CPNA-25": (False, 5.0, 0.25, False),
    "CPNA-75": (False, 5.0, 0.75, False),
    "CPNC-50": (False, 5.0, 0.50, True),
}
SPEEDS_KMH = tuple(float(v) for v in range(20, 65, 5))
# car-to-car: test -> (target speed km/h, test-car speeds km/h)
CAR_TESTS = {
    "CCRs": (0.0, tuple(float(v) for v in range(10, 55, 5))),
    "CCRm": (20.0, tuple(float(v) for v in range(30, 85, 5))),
    "CCRb": (50.0, (50.0,)),
}
OVERLAPS_PCT = (-75.0, -50.0, 50.0, 75.0, 100.0)
CCRB_VARIANTS = ((2.0, 12.0), (2.0, 40.0), (6.0, 12.0), (6.0, 40.0))  # (target deceleration m/s², gap m)
# points per impact (relative) speed band, km/h (confirmed for CCRs at 50 km/h and full avoidance at 20 km/h and
# below; docs/design.md §10)
POINT_BANDS = ((5.0, 1.0), (15.0, 0.75), (30.0, 0.5), (40.0, 0.25))
START_TTC_S = 4.0
ACCELERATION_M = 1.0
AFTER_TTC_S = 3.0
CAR_WIDTH, PARKED_LENGTH, PARKED_WIDTH = 1.8, 4.5, 1.8
ENDS = ("impact", "stop", "pass")
STOPPED_MS = 1e-3
# Euro NCAP's 2015 pedestrian aim: avoid up to 40 km/h; from 40 to 60 km/h, impact below 40 km/h
AVOID_UP_TO_KMH, IMPACT_BELOW_KMH = 40.0, 40.0


@dataclass(frozen=True)
class NcapSpec(FamilySpec):
    """One Euro NCAP test run: ``test`` (a key of :data:`TESTS` or :data:`CAR_TESTS`) at ``speed_kmh``; for the car
    tests the ``overlap_pct`` and, for CCRb, the target's deceleration (m/s²) and the bumper gap (m); seed: the
    street layout."""

    test: str
    speed_kmh: float
    seed: int = 0
    overlap_pct: float = 100.0
    target_decel: float = 0.0
    gap_m: float = 0.0
    family: str = FAMILY

    def __post_init__(self):
        if self.family != FAMILY:
            raise ValueError(f"scenario field family={self.family!r}: an NcapSpec is family {FAMILY!r}")
        if self.test not in TESTS and self.test not in CAR_TESTS:
            raise ValueError(f"scenario field test={self.test!r}: use one of {', '.join([*TESTS, *CAR_TESTS])}")
        if not (0.0 < abs(self.overlap_pct) <= 100.0):
            raise ValueError(f"scenario field overlap_pct={self.overlap_pct!r}: it must be in [-100, 0) or (0, 100]")
        if self.test == "CCRb" and not (self.target_decel > 0.0 and self.gap_m > 0.0):
            raise ValueError(
                f"scenario field target_decel={self.target_decel!r} / gap_m={self.gap_m!r}: CCRb needs both > 0"
            )
        if not 0.0 < self.speed_kmh <= 150.0 or self.speed_kmh != self.speed_kmh:
            raise ValueError(f"scenario field speed_kmh={self.speed_kmh!r} is out of range: it must be in (0, 150]")
        if int(self.seed) != self.seed or self.seed < 0:
            raise ValueError(f"scenario field seed={self.seed!r} must be a non-negative integer")

    @property
    def ego_speed(self) -> float:
        return self.speed_kmh / 3.6

    @property
    def car_test(self) -> bool:
        return self.test in CAR_TESTS

    @property
    def hazard(self) -> str:
        return "car" if self.car_test else "pedestrian"

    @property
    def ttc(self) -> float:
        return START_TTC_S

    @property
    def walking_speed(self) -> float:
        return TESTS[self.test][1] / 3.6

    @property
    def variant(self) -> str:
        """The car test's parameters as a label ("" for a pedestrian test)."""
        if self.test == "CCRb":
            return f"{self.target_decel:g} m/s², {self.gap_m:g} m"
        return f"{self.overlap_pct:+g} %" if self.car_test else ""


SPEC = NcapSpec


def bank(tests=tuple(TESTS), speeds_kmh=SPEEDS_KMH, seed: int = 0) -> list[NcapSpec]:
    """The fixed bank: every test at every speed, on one street layout."""
    return [NcapSpec(t, float(v), seed) for t in tests for v in speeds_kmh]


def car_bank(tests=tuple(CAR_TESTS), overlaps=OVERLAPS_PCT, speed_step_kmh: float = 5.0, seed: int = 0):
    """The car-to-car runs: CCRs and CCRm at every ``speed_step_kmh`` of their range and every overlap, CCRb's four
    variants."""
    out = []
    for test in tests:
        speeds = CAR_TESTS[test][1]
        lo = speeds[0]
        speeds = [v for v in speeds if abs((v - lo) / speed_step_kmh - round((v - lo) / speed_step_kmh)) < 1e-9]
        if test == "CCRb":
            out += [NcapSpec(test, v, seed, 100.0, d, g) for v in speeds for d, g in CCRB_VARIANTS]
        else:
            out += [NcapSpec(test, v, seed, float(o)) for v in speeds for o in overlaps]
    return out


def sample(rng: np.random.Generator) -> NcapSpec:
    return NcapSpec(str(rng.choice(list(TESTS))), float(rng.choice(SPEEDS_KMH)), int(rng.integers(0, 2**31 - 1)))


@dataclass
class NcapState:
    """The test's pedestrian: where its path crosses the car's (``ped_x``), when it starts to walk, and whether it
    has. Hooks as in ``envs.chae.ChaeState``."""

    ped_x: float
    start_t: float
    velocity: tuple[float, float]
    started: bool = False
    horizon_s: float = START_TTC_S + AFTER_TTC_S

    def substep(self, actors: Actors, bumper_before: float, bumper_after: float, t0: float, tau: float, sub_dt: float):
        """Start walking at ``start_t``, exactly: positions inside a step are ``xy + vel * tau`` from the step's
        start ``t0``, so the start point is moved back by the walk's would-be distance from ``t0`` to ``start_t``."""
        if self.started or t0 + tau < self.start_t:
            return
        self.started = True
        vel = np.asarray(self.velocity)
        actors.ped_vel[0] = vel
        actors.ped_xy[0] -= vel * (self.start_t - t0)

    def context(self, actors: Actors, bumper_x: float, ego=None) -> dict:
        return {}

    def ttc(self, t: float, ego) -> float:
        """The nominal time to the impact point: the test's clock."""
        return START_TTC_S - t

    def end(self, actors: Actors, bumper_x: float, speed: float, ctx: dict, ego=None) -> str | None:
        if not actors.ped_active[0]:
            return "impact"
        if speed <= STOPPED_MS:
            return "stop"
        if bumper_x > self.ped_x + PARKED_LENGTH:  # the whole car is past the path
            return "pass"
        return None

    def outcome(self, spec: NcapSpec, bumper_x: float) -> dict:
        return {"family": FAMILY, "test": spec.test, "gap_to_pedestrian": float(self.ped_x - bumper_x)}


@dataclass
class CarTestState:
    """A car-to-car test's target (``motion``, car 0 of the pool); hooks as in ``NcapState``."""

    motion: Motion
    ego_half_length: float
    horizon_s: float = START_TTC_S + AFTER_TTC_S
    t: float = 0.0

    def substep(self, actors: Actors, bumper_before: float, bumper_after: float, t0: float, tau: float, sub_dt: float):
        x, y, h = self.motion.pose(t0 + tau)
        actors.car_vel[0] = ((x - actors.car_xy[0, 0]) / tau, (y - actors.car_xy[0, 1]) / tau)
        actors.car_heading[0] = h
        self.t = t0 + tau

    def target_speed(self, t: float) -> float:
        m = self.motion
        return max(0.0, m.speed - m.decel * t) if m.decel > 0 else m.speed

    def ttc(self, t: float, ego) -> float:
        """Bumper gap over closing speed at the current speeds (inf while not closing)."""
        x, _, _ = self.motion.pose(t)
        gap = x - PARKED_LENGTH / 2 - (ego.x + self.ego_half_length)
        closing = ego.v - self.target_speed(t)
        return gap / closing if closing > 1e-9 else math.inf

    def context(self, actors: Actors, bumper_x: float, ego=None) -> dict:
        return {}

    def end(self, actors: Actors, bumper_x: float, speed: float, ctx: dict, ego=None) -> str | None:
        if speed <= STOPPED_MS:
            return "stop"
        if speed < self.target_speed(self.t) - 1e-9:
            return "slower"
        return None

    def outcome(self, spec: NcapSpec, bumper_x: float) -> dict:
        x, _, _ = self.motion.pose(self.t)
        return {"family": FAMILY, "test": spec.test, "gap_to_target": float(x - PARKED_LENGTH / 2 - bumper_x)}


def build_car_test(spec: NcapSpec, ego_front: float) -> tuple[Actors, CarTestState]:
    v, u = spec.ego_speed, CAR_TESTS[spec.test][0] / 3.6
    gap = spec.gap_m if spec.test == "CCRb" else (v - u) * START_TTC_S
    offset = math.copysign((1.0 - abs(spec.overlap_pct) / 100.0) * CAR_WIDTH, spec.overlap_pct)
    motion = Motion(ego_front + gap + PARKED_LENGTH / 2, EGO_LANE_Y - offset, 0.0, u, decel=spec.target_decel)
    actors = Actors.empty(collision_point=(ego_front + gap, EGO_LANE_Y))
    actors.car_xy[0] = (motion.x0, motion.y0)
    actors.car_active[0] = actors.car_hazard[0] = True
    return actors, CarTestState(motion, ego_half_length=ego_front)  # the ego starts with its centre at x = 0


def build(spec: NcapSpec, ego_front: float, **options):
    if spec.car_test:
        return build_car_test(spec, ego_front)
    far, walk_kmh, share, parked = TESTS[spec.test]
    v, v_p = spec.ego_speed, walk_kmh / 3.6
    ped_x = ego_front + v * START_TTC_S
    direction = -1.0 if far else 1.0  # near side: the ego's kerb, y < 0, walking towards +y
    impact_y = EGO_LANE_Y - direction * CAR_WIDTH / 2 + direction * share * CAR_WIDTH
    walk = v_p * START_TTC_S - ACCELERATION_M  # covered in 4 s when the first 1 m is an acceleration from rest
    start_y = impact_y - direction * walk
    actors = Actors.empty(collision_point=(ped_x, impact_y))
    actors.ped_xy[0] = (ped_x, start_y)
    actors.ped_active[0] = actors.ped_hazard[0] = True
    actors.ped_stop_y[0] = direction * (ROAD_HALF_WIDTH + 1.0)  # walks on to the far pavement
    if parked:
        kerb_y = -(ROAD_HALF_WIDTH + 0.2)  # straddling the kerb, 0.15 m clear of a car in its lane
        first = ped_x - 1.0 - PARKED_LENGTH / 2
        actors.car_xy[0] = (first, kerb_y)
        actors.car_xy[1] = (first - PARKED_LENGTH - 1.0, kerb_y)
        actors.car_active[:2] = True
    state = NcapState(ped_x=ped_x, start_t=1.0 / v_p * ACCELERATION_M, velocity=(0.0, direction * v_p))
    return actors, state


def car_points(speed_kmh: float, impact_kmh: float | None) -> tuple[float, bool]:
    """(points in [0, 1], confirmed) for one car-to-car run by its relative impact speed: full avoidance scores 1;
    at 20 km/h and below only avoidance scores; above, the bands of CCRs at 50 km/h (< 5 km/h: 1, < 15: 0.75,
    < 30: 0.5, < 40: 0.25). Confirmed at 50 km/h and at 20 km/h and below; elsewhere approximate."""
    confirmed = speed_kmh <= 20.0 or speed_kmh == 50.0
    if impact_kmh is None:
        return 1.0, confirmed
    if speed_kmh <= 20.0:
        return 0.0, confirmed
    return next((p for band, p in POINT_BANDS if impact_kmh < band), 0.0), confirmed


def verdict(speed_kmh: float, impact_kmh: float | None) -> str:
    """Euro NCAP's 2015 pedestrian aim for one run: ``pass`` or ``fail`` (approximate: not the scoring table)."""
    if impact_kmh is None:
        return "pass"
    if speed_kmh <= AVOID_UP_TO_KMH:
        return "fail"
    return "pass" if impact_kmh < IMPACT_BELOW_KMH else "fail"
