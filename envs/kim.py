"""Scenario family ``kim``: Kim et al. 2020, red-light runners at a four-way junction (docs/design.md §10).

The ego drives through a junction on green (towards +x, at U(10, 50) km/h, in either of its two lanes) while a car
runs the red light at 60 km/h:

* ``right``: the runner comes from the ego's right (from y < 0, driving towards +y), in either lane;
* ``left``: from the ego's left (from y > 0, towards -y), in either lane;
* ``left_turn``: from the right, turning left across the ego's lanes on a 12 m arc into the oncoming inner lane.

The episode starts at the takeover, and the runner is placed so that at constant speeds its footprint first
touches the ego's exactly 1.0 s later: in ``right`` and ``left`` its front meets the middle of the ego's flank; in
``left_turn`` the ego's centre would be where the arc crosses the ego's lane centre 1.0 s later, and the runner is
placed along its path (by bisection to 1 mm) so that the footprints start to overlap then.

With p = 0.5 neutral cars are present: a follower in the ego's lane at a time headway of U(1, 2) s, which brakes at
6 m/s² one second after the ego has slowed by 0.5 m/s (so that braking hard can get the ego rear-ended); one car
waiting at each side street's stop line, in a lane the runner does not use; and one or two oncoming cars. Any
collision counts as a failure, as in the paper; an episode ends at the first crash, at the goal (the ego's centre
within 2 m of the point 30 m past the junction's centre in its starting lane) or after 5 s.

Geometry (our choices, documented in docs/design.md §10): both roads have two 3.5 m lanes per direction (|y| < 7
and |x - x_junction| < 7); 3 m sidewalks, a building on each corner block 1 m behind them, and a pole at each corner
and along the kerbs. The camera draws it: the ground per pixel (``camera.CrossroadsGround``: both roads with their
lane lines and stop lines, sidewalks everywhere else), pooled building boxes along each block's faces to the roads,
the poles and the cars.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from . import geometry
from .actors import Actors
from .scene import BUILDINGS, POLES, TEMPLATES, StaticLayout
from .specs import FamilySpec
from .streams import KIM_BUILDING_HEIGHTS, KIM_NEUTRAL_CARS

FAMILY = "kim"
SCENARIOS = ("right", "left", "left_turn")
LANE_WIDTH = 3.5
LANES = (1.75, 5.25)  # lane centres' distance from the road's centre line: inner, outer
ROAD_HALF_WIDTH = 2 * LANE_WIDTH
SIDEWALK_M = 3.0
RUNNER_SPEED = 60.0 / 3.6
EGO_SPEED_RANGE = (10.0 / 3.6, 50.0 / 3.6)
CONTACT_S = 1.0
TURN_RADIUS_M = 12.0
GOAL_PAST_CENTRE_M, GOAL_RADIUS_M = 30.0, 2.0
MAX_EPISODE_S = 5.0
FOLLOWER_HEADWAY_S = (1.0, 2.0)
FOLLOWER_DECEL, FOLLOWER_REACTION_S, SLOWED_BY_MS = 6.0, 1.0, 0.5
CAR_LENGTH, CAR_WIDTH = 4.5, 1.8  # every car's footprint is the ego's (envs/vehicle.py)
ENDS = ("goal",)


@dataclass(frozen=True)
class KimSpec(FamilySpec):
    """One Kim scenario. scenario: right, left or left_turn; ego_speed (m/s) at the takeover; ego_lane and
    runner_lane: 0 inner, 1 outer (a left turn starts from the inner lane whatever runner_lane says); neutral:
    neutral cars present; seed: the neutral cars' draw and the street furniture. impact_offset (m): where the
    runner's path crosses the ego at the contact time, forward of the ego's centre (0: the middle of its flank, our
    reading of the paper; +2.25 its front bumper, -2.25 its rear), for the sensitivity of every result to a
    placement the paper does not describe; the training distribution keeps 0 unless asked (``sample``)."""

    seed: int
    scenario: str
    ego_speed: float
    ego_lane: int = 0
    runner_lane: int = 0
    neutral: bool = False
    impact_offset: float = 0.0
    family: str = FAMILY

    def __post_init__(self):
        if self.family != FAMILY:
            raise ValueError(f"scenario field family={self.family!r}: a KimSpec is family {FAMILY!r}")
        if self.scenario not in SCENARIOS:
            raise ValueError(f"scenario field scenario={self.scenario!r}: use one of {', '.join(SCENARIOS)}")
        if not 0.0 < self.ego_speed <= 40.0 or self.ego_speed != self.ego_speed:
            raise ValueError(f"scenario field ego_speed={self.ego_speed!r} is out of range: it must be in (0, 40]")
        for name in ("ego_lane", "runner_lane"):
            if getattr(self, name) not in (0, 1):
                raise ValueError(f"scenario field {name}={getattr(self, name)!r} must be 0 (inner) or 1 (outer)")
        if not isinstance(self.neutral, bool):
            raise ValueError(f"scenario field neutral={self.neutral!r} must be true or false")
        if int(self.seed) != self.seed or self.seed < 0:
            raise ValueError(f"scenario field seed={self.seed!r} must be a non-negative integer")
        if not abs(self.impact_offset) <= CAR_LENGTH / 2:
            raise ValueError(
                f"scenario field impact_offset={self.impact_offset!r} must be within the ego's length: "
                f"[{-CAR_LENGTH / 2}, {CAR_LENGTH / 2}] m from its centre"
            )

    @property
    def ego_y(self) -> float:
        return -LANES[self.ego_lane]

    @property
    def hazard(self) -> str:
        return "car"

    @property
    def ttc(self) -> float:
        return CONTACT_S


SPEC = KimSpec


def sample(rng: np.random.Generator, impact_offset_spread: float = 0.0) -> KimSpec:
    """The training distribution: scenario, lanes and neutral cars uniform, ego speed U(10, 50) km/h. With
    ``impact_offset_spread`` > 0 the runner's path also crosses the ego uniformly within that many metres of the
    middle of its flank (kept on the ego), drawn last, so the other fields are those of the spread-free draw."""
    spec = KimSpec(
        seed=int(rng.integers(0, 2**31 - 1)),
        scenario=str(SCENARIOS[int(rng.integers(len(SCENARIOS)))]),
        ego_speed=float(rng.uniform(*EGO_SPEED_RANGE)),
        ego_lane=int(rng.integers(2)),
        runner_lane=int(rng.integers(2)),
        neutral=bool(rng.random() < 0.5),
    )
    if impact_offset_spread < 0:
        raise ValueError(f"impact_offset_spread={impact_offset_spread!r} must be >= 0 m")
    if impact_offset_spread == 0:
        return spec
    reach = min(float(impact_offset_spread), CAR_LENGTH / 2)
    return replace(spec, impact_offset=float(rng.uniform(-reach, reach)))


# ----------------------------------------------------------------------------- paths
@dataclass(frozen=True)
class Path:
    """A scripted car's path in the junction's frame (x from the junction's centre): a straight approach along
    ``heading0`` through ``start``, optionally a left-turning arc of ``radius`` through ``turn`` rad beginning at
    arc length 0, then straight on. ``pose(s)`` gives (x, y, heading) at arc length s (negative before the arc)."""

    start: tuple[float, float]  # where arc length 0 is
    heading0: float
    radius: float = 0.0
    turn: float = 0.0

    def pose(self, s: float) -> tuple[float, float, float]:
        x0, y0 = self.start
        h = self.heading0
        if s <= 0.0 or self.turn == 0.0:
            return x0 + s * math.cos(h), y0 + s * math.sin(h), h
        arc = self.radius * self.turn
        # left turn: the centre lies to the left of the heading
        cx, cy = x0 - self.radius * math.sin(h), y0 + self.radius * math.cos(h)
        a = min(s, arc) / self.radius
        x, y = cx + self.radius * math.sin(h + a), cy - self.radius * math.cos(h + a)
        if s <= arc:
            return x, y, h + a
        h2 = h + self.turn
        return x + (s - arc) * math.cos(h2), y + (s - arc) * math.sin(h2), h2


def runner_path(spec: KimSpec) -> Path:
    lane = LANES[spec.runner_lane]
    if spec.scenario == "right":
        return Path((lane, 0.0), math.pi / 2)
    if spec.scenario == "left":
        return Path((-lane, 0.0), -math.pi / 2)
    # from the right's inner lane, turning left into the oncoming inner lane (y = +1.75)
    return Path((LANES[0], LANES[0] - TURN_RADIUS_M), math.pi / 2, TURN_RADIUS_M, math.pi / 2)


def _lane_crossing(path: Path, y: float) -> float:
    """Arc length at which ``path``'s centre line crosses the line y (the path crosses it once)."""
    lo, hi = -100.0, 100.0
    below = path.pose(lo)[1] < y
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if (path.pose(mid)[1] < y) == below:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def _touching(ego_x: float, ego_y: float, pose: tuple[float, float, float]) -> bool:
    x, y, h = pose
    hl, hw = CAR_LENGTH / 2, CAR_WIDTH / 2
    return geometry.rect_rect(ego_x, ego_y, 1.0, 0.0, hl, hw, x, y, math.cos(h), math.sin(h), hl, hw)


def place_runner(spec: KimSpec, ego_x0: float) -> tuple[float, Path, float]:
    """(junction x, the runner's path, its arc length at the takeover) such that, at constant speeds, the runner's
    and the ego's footprints first touch ``CONTACT_S`` after the takeover (the ego's centre starts at ``ego_x0``)."""
    path, y = runner_path(spec), spec.ego_y
    ego_at_contact = ego_x0 + spec.ego_speed * CONTACT_S
    crossed_at = ego_at_contact + spec.impact_offset  # default: the runner's lane meets the middle of the ego's flank
    if spec.scenario == "left_turn":
        s_cross = _lane_crossing(path, y)
        junction_x = crossed_at - path.pose(s_cross)[0]
    else:
        junction_x = crossed_at - path.start[0]
        s_cross = (y - path.start[1]) / math.sin(path.heading0)

    def touching_at_contact(s_at_contact: float) -> bool:
        x, yy, h = path.pose(s_at_contact)
        return _touching(ego_at_contact - junction_x, y, (x, yy, h))

    # At the crossing the footprints overlap; 10 m earlier along the path they do not. The first s that touches is
    # the one where contact begins at CONTACT_S (the runner approaches the ego's footprint monotonically).
    lo, hi = s_cross - 10.0, s_cross
    if touching_at_contact(lo) or not touching_at_contact(hi):
        raise RuntimeError(f"cannot place the runner for {spec}")
    while hi - lo > 1e-3:
        mid = 0.5 * (lo + hi)
        if touching_at_contact(mid):
            hi = mid
        else:
            lo = mid
    return junction_x, path, hi - RUNNER_SPEED * CONTACT_S


# ----------------------------------------------------------------------------- the episode's state
@dataclass
class ScriptedCar:
    """Car ``index`` of the pool following ``path`` (junction frame) from arc length ``s0`` at ``speed``."""

    index: int
    path: Path
    s0: float
    speed: float
    brakes: bool = False  # the follower: decelerates once the ego has slowed

    def arc_length(self, t: float, brake_from: float | None) -> float:
        if not self.brakes or brake_from is None or t <= brake_from:
            return self.s0 + self.speed * t
        s_b = self.s0 + self.speed * brake_from
        dt = min(t - brake_from, self.speed / FOLLOWER_DECEL)
        return s_b + self.speed * dt - 0.5 * FOLLOWER_DECEL * dt * dt


@dataclass
class KimState:
    """The junction, the scripted cars and the goal; hooks as in ``envs.chae.ChaeState``."""

    junction_x: float
    ego_v0: float
    goal: tuple[float, float]
    cars: list[ScriptedCar] = field(default_factory=list)
    slowed_at: float | None = None
    last_goal_distance: float = math.nan
    horizon_s: float = MAX_EPISODE_S

    @property
    def brake_from(self) -> float | None:
        return None if self.slowed_at is None else self.slowed_at + FOLLOWER_REACTION_S

    def substep(self, actors: Actors, bumper_before: float, bumper_after: float, t0: float, tau: float, sub_dt: float):
        """Move every scripted car to where its path puts it at t0 + tau: the env places cars at ``xy + vel * tau``
        within a step, so the velocity is set to reach that point exactly (and ``advance`` lands on it)."""
        if self.slowed_at is None and (bumper_after - bumper_before) / sub_dt < self.ego_v0 - SLOWED_BY_MS:
            self.slowed_at = t0 + tau
        for car in self.cars:
            x, y, h = car.path.pose(car.arc_length(t0 + tau, self.brake_from))
            i = car.index
            actors.car_vel[i] = ((x + self.junction_x - actors.car_xy[i, 0]) / tau, (y - actors.car_xy[i, 1]) / tau)
            actors.car_heading[i] = h

    def goal_distance(self, ego) -> float:
        return math.hypot(ego.x - self.goal[0], ego.y - self.goal[1])

    def context(self, actors: Actors, bumper_x: float, ego=None) -> dict:
        """The progress to the goal this step (Eq. 10's d_{t-1} - d_t)."""
        d = self.goal_distance(ego)
        progress = self.last_goal_distance - d
        self.last_goal_distance = d
        return {"goal_progress": progress, "goal_distance": d}

    def end(self, actors: Actors, bumper_x: float, speed: float, ctx: dict, ego=None) -> str | None:
        return "goal" if ctx["goal_distance"] <= GOAL_RADIUS_M else None

    def outcome(self, spec: KimSpec, bumper_x: float) -> dict:
        return {
            "family": FAMILY,
            "scenario": spec.scenario,
            "neutral": int(spec.neutral),
            "goal_distance": float(self.last_goal_distance),
        }


def build(spec: KimSpec, ego_front: float) -> tuple[Actors, KimState]:
    """The runner and, if ``spec.neutral``, the neutral cars, at the takeover (the ego's centre at x = 0)."""
    ego_x0 = ego_front - CAR_LENGTH / 2
    junction_x, path, s0 = place_runner(spec, ego_x0)
    rng = np.random.default_rng([spec.seed, KIM_NEUTRAL_CARS])
    cars = [ScriptedCar(0, path, s0, RUNNER_SPEED)]
    hazard = [True]
    if spec.neutral:
        v = spec.ego_speed
        # the follower: bumper-to-bumper gap = speed x headway, in the ego's lane, at the ego's speed
        gap = v * float(rng.uniform(*FOLLOWER_HEADWAY_S))
        cars.append(ScriptedCar(1, Path((ego_x0 - CAR_LENGTH - gap - junction_x, spec.ego_y), 0.0), 0.0, v, True))
        # waiting at the stop lines (1 m before the crossing road's edge), in lanes the runner does not use
        free = int(rng.integers(2))
        right_lane = {"right": 1 - spec.runner_lane, "left": free, "left_turn": 1}[spec.scenario]
        left_lane = 1 - spec.runner_lane if spec.scenario == "left" else free
        stop = ROAD_HALF_WIDTH + 1.0 + CAR_LENGTH / 2
        cars.append(ScriptedCar(2, Path((LANES[right_lane], -stop), math.pi / 2), 0.0, 0.0))
        cars.append(ScriptedCar(3, Path((-LANES[left_lane], stop), -math.pi / 2), 0.0, 0.0))
        # oncoming traffic, towards -x, somewhere ahead
        x = float(rng.uniform(15.0, 40.0))
        for k in range(1 + int(rng.integers(2))):
            lane = LANES[int(rng.integers(2))]
            cars.append(ScriptedCar(4 + k, Path((x, lane), math.pi), 0.0, float(rng.uniform(8.0, 14.0))))
            x += float(rng.uniform(15.0, 35.0))
        hazard += [False] * (len(cars) - 1)

    actors = Actors.empty(collision_point=(ego_front + spec.ego_speed * CONTACT_S, spec.ego_y))
    for car, is_hazard in zip(cars, hazard, strict=True):
        x, y, h = car.path.pose(car.s0)
        actors.car_xy[car.index] = (x + junction_x, y)
        actors.car_heading[car.index] = h
        actors.car_active[car.index] = True
        actors.car_hazard[car.index] = is_hazard
    goal = (junction_x + GOAL_PAST_CENTRE_M, spec.ego_y)
    state = KimState(junction_x, spec.ego_speed, goal, cars)
    state.last_goal_distance = goal[0] - ego_x0  # the ego starts in its lane, on the goal's line
    return actors, state


def layout(spec: KimSpec, state: KimState, rng: np.random.Generator) -> StaticLayout:
    """The junction's obstacles: a building on each corner block behind the sidewalks, a pole at each corner and
    poles along the kerbs every 20-30 m; and, for the camera, pooled bodies that draw them (``render_placements``)."""
    jx = state.junction_x
    kerb = ROAD_HALF_WIDTH
    rects, circles = [], []
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            inner = kerb + SIDEWALK_M + 1.0 + float(rng.uniform(0.0, 3.0))
            half = 30.0
            rects.append((jx + sx * (inner + half), sy * (inner + half), half, half, BUILDINGS))
            circles.append((jx + sx * (kerb + 0.6), sy * (kerb + 0.6), 0.12, POLES))
    for sy in (-1.0, 1.0):
        x = jx - 60.0 + float(rng.uniform(0.0, 20.0))
        while x < jx + 80.0:
            if abs(x - jx) > kerb + 2.0:
                circles.append((x, sy * (kerb + 0.35), 0.12, POLES))
            x += float(rng.uniform(20.0, 30.0))
    rects_a = np.array(rects, dtype=np.float64).reshape(-1, 5)
    circles_a = np.array(circles, dtype=np.float64).reshape(-1, 4)
    return StaticLayout(
        junction_x=jx,
        placements=render_placements(jx, rects_a, circles_a, np.random.default_rng([spec.seed, KIM_BUILDING_HEIGHTS])),
        rects=rects_a,
        circles=circles_a,
        crossroads_half_width=ROAD_HALF_WIDTH,
    )


BLOCK_BOXES = {1.0: (3, 4), -1.0: (2, 3)}  # per side of the junction (ahead, behind): long boxes, short boxes


def render_placements(jx: float, rects: np.ndarray, circles: np.ndarray, rng: np.random.Generator) -> dict:
    """Pooled bodies that draw the layout for the camera (``envs.bodies``), inside the collision footprints so the
    picture never shows a wall where none stands: along each corner block's face to the main road, long building
    boxes from the corner outwards; along its face to the cross road, short ones beyond the first long box; heights
    U(6, 24) m from ``rng`` (its own generator: the collision layout's draws are unchanged). The blocks behind
    the junction get fewer boxes, as less of them is in view. Every pole footprint gets a pole."""
    placed: dict[str, list] = {"building_long": [], "building_short": [], "pole": []}
    for cx, cy, hx, hy, _ in rects:
        sx, sy = np.sign(cx - jx), np.sign(cy)
        inner_x, inner_y = abs(cx - jx) - hx, abs(cy) - hy
        n_long, n_short = BLOCK_BOXES[sx]
        lx, ly, lz = TEMPLATES["building_long"].size
        for k in range(n_long):
            placed["building_long"].append(
                (jx + sx * (inner_x + lx * (2 * k + 1)), sy * (inner_y + ly), rng.uniform(6.0, 24.0) - lz)
            )
        bx, by, bz = TEMPLATES["building_short"].size
        for k in range(n_short):
            placed["building_short"].append(
                (jx + sx * (inner_x + bx), sy * (inner_y + 2 * ly + by * (2 * k + 1)), rng.uniform(6.0, 24.0) - bz)
            )
    _, pole_height = TEMPLATES["pole"].size
    placed["pole"] = [(x, y, pole_height / 2) for x, y, _, cls in circles if cls == POLES]
    for name, spots in placed.items():
        if len(spots) > TEMPLATES[name].count:
            raise RuntimeError(
                f"the kim layout asks for {len(spots)} {name} bodies; the pool holds {TEMPLATES[name].count}"
            )
    return placed


# ----------------------------------------------------------------------------- actions and baselines
V_DES_MAX, STEER_ANGLE_MAX = 60.0 / 3.6, 0.6


def kim_action(action, speed: float) -> np.ndarray:
    """Kim's action (desired speed, steering angle), given as two numbers in [-1, 1] (an actor's tanh outputs),
    as our [steer, pedal]: v_des = (a0 + 1) / 2 * 16.67 m/s, alpha = 0.6 a1 rad, steer = alpha / 0.6 and
    pedal = clip(0.5 (v_des - v), -1, 1) (our default, docs/design.md §10: a proportional speed controller)."""
    a = np.clip(np.asarray(action, dtype=np.float64).reshape(2), -1.0, 1.0)
    v_des = 0.5 * (a[0] + 1.0) * V_DES_MAX
    return np.array([a[1], min(1.0, max(-1.0, 0.5 * (v_des - speed)))], dtype=np.float32)


def kim_action_for(control, speed: float) -> np.ndarray:
    """The inverse of ``kim_action``: the (desired speed, steering angle) pair in [-1, 1] that asks for our
    [steer, pedal] ``control`` at ``speed``, so that a planner's controls can be demonstrated to Kim's actor. A
    saturated pedal asks for the extreme desired speed (0 or 16.67 m/s), which keeps it saturated as the speed
    changes; a pedal the controller cannot give (full braking below 2 m/s) maps to the nearest it can."""
    steer, pedal = (float(x) for x in np.clip(np.asarray(control, dtype=np.float64).reshape(2), -1.0, 1.0))
    if pedal <= -1.0:
        v_des = 0.0
    elif pedal >= 1.0:
        v_des = V_DES_MAX
    else:
        v_des = min(V_DES_MAX, max(0.0, speed + 2.0 * pedal))
    return np.array([2.0 * v_des / V_DES_MAX - 1.0, steer], dtype=np.float32)


class Aeb3m:
    """Kim's AEB baseline: hold speed, and brake fully (for good) once any footprint enters the box 3 m long and one
    car wide ahead of the front bumper. Privileged: it reads the footprints, as a perfect sensor would."""

    name = "aeb3m"
    box_m = 3.0

    def reset(self, seed=None) -> None:
        self.braking = False

    def bind(self, env) -> None:
        self.env = env

    def act(self, obs, info) -> np.ndarray:
        if not self.braking:
            self.braking = obstacle_ahead(self.env, self.box_m)
        return np.array([0.0, -1.0 if self.braking else 0.0], dtype=np.float32)


def obstacle_ahead(env, length_m: float) -> bool:
    """Whether a car, pedestrian or static footprint lies in the box ``length_m`` long, one car wide, just ahead of
    the ego's front bumper."""
    ego, act, hl, hw = env.ego, env.actors, env.params.length / 2, env.params.width / 2
    c, s = math.cos(ego.psi), math.sin(ego.psi)
    bx, by = ego.x + (hl + length_m / 2) * c, ego.y + (hl + length_m / 2) * s
    half = length_m / 2
    for i in np.flatnonzero(act.car_active):
        h = act.car_heading[i]
        if geometry.rect_rect(bx, by, c, s, half, hw, *act.car_xy[i], math.cos(h), math.sin(h), hl, hw):
            return True
    for cx, cy, hx, hy, _ in env.layout.rects:
        if geometry.rect_rect(bx, by, c, s, half, hw, cx, cy, 1.0, 0.0, hx, hy):
            return True
    for cx, cy, r, _ in env.layout.circles:
        if geometry.rect_circle(bx, by, c, s, half, hw, cx, cy, r):
            return True
    return False
