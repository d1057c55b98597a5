"""Scenario family ``chae``: Chae et al. 2017, "Autonomous braking system via deep reinforcement learning".

A straight road; the ego drives from x = 0 at ``v_init``. A pedestrian stands 0.5 m beyond the kerb, on the near
side (the ego's lane's side) or the far side, at 5·v_init ahead of the ego's front bumper. In Scenario 1 it
starts to cross when the bumper passes p_trig = (5 − TTC)·v_init, i.e. TTC seconds before the bumper reaches the
pedestrian's x at constant speed, and walks straight across at ``v_ped``; in Scenario 2 it stays. An episode ends on

* **bump**: the bumper passes the safety line, 3 m before the pedestrian's x, while the pedestrian is crossing
  (inside the carriageway);
* **stop**: the ego stands still (in Scenario 2, an unnecessary stop);
* **pass**: the bumper passes the pedestrian's x;
* **cross**: the pedestrian reaches the far side,

or after 12 s. The paper steps every 0.1 s (``env.step_s``; ``conf/env`` sets it for this family). Footprint contact
with the pedestrian is still registered (impact speed, Rosén injury), since "bump" is only Chae's proxy.

Our choices where the paper is silent (listed in docs/design.md): our street's two 3.5 m lanes, x measured from the
front bumper, the pedestrian crossing at a right angle, no other traffic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .actors import CAR_POOL, PEDESTRIAN_POOL, Actors
from .scene import EGO_LANE_Y, ROAD_HALF_WIDTH
from .specs import FamilySpec

FAMILY = "chae"
V_INIT_RANGE = (10.0 / 3.6, 60.0 / 3.6)  # 10-60 km/h
TTC_RANGE = (1.5, 4.0)
V_PED_RANGE = (2.0, 4.0)
SAFETY_LINE_M = 3.0
START_BEYOND_KERB_M = 0.5
MAX_EPISODE_S = 12.0
STEP_S = 0.1
STOPPED_MS = 1e-3
ENDS = ("bump", "stop", "pass", "cross")
# Eq. 8: r_t = -(alpha * dx^2 + beta) * decel - (eta * v_t^2 + lambda) * 1[bump]
ALPHA, BETA, ETA, LAMBDA = 0.001, 0.1, 0.01, 100.0
_LIMITS = {"ttc": (0.0, 10.0), "v_init": (0.0, 40.0), "v_ped": (0.0, 10.0)}


@dataclass(frozen=True)
class ChaeSpec(FamilySpec):
    """One Chae scenario. ttc (s), v_init and v_ped (m/s); far_side: the pedestrian starts on the oncoming lane's
    side; crosses: Scenario 1 (True) or 2 (False). seed: the street layout."""

    seed: int
    ttc: float
    v_init: float
    v_ped: float = 3.0
    far_side: bool = False
    crosses: bool = True
    family: str = FAMILY

    def __post_init__(self):
        if self.family != FAMILY:
            raise ValueError(f"scenario field family={self.family!r}: a ChaeSpec is family {FAMILY!r}")
        for name, (lo, hi) in _LIMITS.items():
            value = getattr(self, name)
            if not (lo < value <= hi) or value != value:
                raise ValueError(f"scenario field {name}={value!r} is out of range: it must be in ({lo}, {hi}]")
        if int(self.seed) != self.seed or self.seed < 0:
            raise ValueError(f"scenario field seed={self.seed!r} must be a non-negative integer")
        for name in ("far_side", "crosses"):
            if not isinstance(getattr(self, name), bool | np.bool_):
                raise ValueError(f"scenario field {name}={getattr(self, name)!r} must be true or false")

    # what the env and the reports read from any family
    @property
    def ego_speed(self) -> float:
        return self.v_init

    @property
    def hazard(self) -> str:
        return "pedestrian"


def sample_chae(
    rng: np.random.Generator, crossing_share: float = 0.5, ttc_range: tuple[float, float] = TTC_RANGE
) -> ChaeSpec:
    """The paper's training distribution (§IV-A): Scenario 1 or 2 and near or far side with p = 0.5 each, TTC
    uniform in ``ttc_range`` (the paper's: 1.5-4 s)."""
    return ChaeSpec(
        seed=int(rng.integers(0, 2**31 - 1)),
        ttc=float(rng.uniform(*ttc_range)),
        v_init=float(rng.uniform(*V_INIT_RANGE)),
        v_ped=float(rng.uniform(*V_PED_RANGE)),
        far_side=bool(rng.random() < 0.5),
        crosses=bool(rng.random() < crossing_share),
    )


SPEC = ChaeSpec
sample = sample_chae


@dataclass
class ChaeState:
    """Where the episode's pedestrian and trigger are (x of the front bumper's line). The env calls its hooks
    (``substep``, ``context``, ``end``, ``outcome``; see ``envs.env``) as it does for every non-porav family."""

    ped_x: float
    trigger_x: float | None  # None: Scenario 2, the pedestrian never starts
    velocity: tuple[float, float]
    start_y: float
    started: bool = False
    horizon_s: float = MAX_EPISODE_S
    # Chae's episodes end at a bump; an evaluation that measures contact and impact speed (bump is only their proxy)
    # sets this False: the bump is recorded and the episode runs on to stop, pass or cross
    end_on_bump: bool = True
    bumped: bool = False

    def substep(self, actors: Actors, bumper_before: float, bumper_after: float, t0: float, tau: float, sub_dt: float):
        trigger(self, actors, bumper_before, bumper_after, tau, sub_dt)

    def context(self, actors: Actors, bumper_x: float, ego=None) -> dict:
        return step_context(self, actors, bumper_x)

    def end(self, actors: Actors, bumper_x: float, speed: float, ctx: dict, ego=None) -> str | None:
        self.bumped |= ctx["bump"]
        if ctx["bump"] and not self.end_on_bump:
            ctx = {**ctx, "bump": False}
        return end_of(self, actors, bumper_x, speed, ctx)

    def outcome(self, spec: ChaeSpec, bumper_x: float) -> dict:
        gap = float(self.ped_x - bumper_x)
        return {"family": FAMILY, "crosses": int(spec.crosses), "gap_to_pedestrian": gap, "bumped": int(self.bumped)}


def build(spec: ChaeSpec, ego_front: float, end_on_bump: bool = True) -> tuple[Actors, ChaeState]:
    """The pedestrian standing at its start, and the trigger that sets it walking."""
    side = 1.0 if spec.far_side else -1.0  # the ego's lane is at y < 0
    start_y = side * (ROAD_HALF_WIDTH + START_BEYOND_KERB_M)
    ped_x = ego_front + 5.0 * spec.v_init
    ped_xy = np.zeros((PEDESTRIAN_POOL, 2))
    ped_xy[0] = (ped_x, start_y)
    ped_active = np.zeros(PEDESTRIAN_POOL, dtype=bool)
    ped_active[0] = True
    ped_hazard = ped_active.copy()
    ped_stop_y = np.full(PEDESTRIAN_POOL, np.nan)
    ped_stop_y[0] = -start_y  # on the far kerb's line
    actors = Actors(
        car_xy=np.zeros((CAR_POOL, 2)),
        car_vel=np.zeros((CAR_POOL, 2)),
        car_heading=np.zeros(CAR_POOL),
        car_active=np.zeros(CAR_POOL, dtype=bool),
        car_hazard=np.zeros(CAR_POOL, dtype=bool),
        ped_xy=ped_xy,
        ped_vel=np.zeros((PEDESTRIAN_POOL, 2)),
        ped_active=ped_active,
        ped_hazard=ped_hazard,
        ped_stop_y=ped_stop_y,
        collision_point=(ped_x, EGO_LANE_Y),
    )
    trigger = ego_front + (5.0 - spec.ttc) * spec.v_init if spec.crosses else None
    state = ChaeState(ped_x, trigger, (0.0, -side * spec.v_ped), start_y, end_on_bump=end_on_bump)
    return actors, state


def trigger(state: ChaeState, actors: Actors, bumper_before: float, bumper_after: float, tau: float, sub_dt: float):
    """Start the pedestrian if the bumper passed the trigger during the sub-step ending ``tau`` seconds into the
    step, at the instant it passed (interpolated within the sub-step). Positions inside a step are ``xy + vel * tau``
    from the step's start, so the start point is moved back by ``vel * t_start``: from then on the pedestrian is
    exactly where a walk that began at ``t_start`` puts it."""
    if state.started or state.trigger_x is None or bumper_after < state.trigger_x:
        return
    state.started = True
    travelled = bumper_after - bumper_before
    late = (bumper_after - state.trigger_x) / travelled if travelled > 0 else 0.0
    t_start = tau - sub_dt * min(1.0, max(0.0, late))
    vel = np.asarray(state.velocity)
    actors.ped_vel[0] = vel
    actors.ped_xy[0] -= vel * t_start


def crossing(state: ChaeState, actors: Actors) -> bool:
    """The pedestrian is walking inside the carriageway."""
    return state.started and abs(actors.ped_xy[0, 1]) < ROAD_HALF_WIDTH


def step_context(state: ChaeState, actors: Actors, bumper_x: float) -> dict:
    """What the ``chae`` reward and the termination read after a step."""
    bump = crossing(state, actors) and bumper_x >= state.ped_x - SAFETY_LINE_M
    return {"dx": state.ped_x - bumper_x, "bump": bool(bump)}


def end_of(state: ChaeState, actors: Actors, bumper_x: float, speed: float, ctx: dict) -> str | None:
    """How the episode ends after this step, if it does: one of :data:`ENDS`."""
    if ctx["bump"]:
        return "bump"
    y = actors.ped_xy[0, 1]
    if state.started and math.copysign(1.0, y) != math.copysign(1.0, state.start_y) and abs(y) >= ROAD_HALF_WIDTH:
        return "cross"
    if speed <= STOPPED_MS:
        return "stop"
    if bumper_x > state.ped_x:
        return "pass"
    return None


def reward(ctx) -> float:
    """Eq. 8 with the published constants; decel = v_{t-1} - v_t (m/s per step). 0 outside this family."""
    fam = ctx.family
    if "dx" not in fam:
        return 0.0
    decel = ctx.speed_before - ctx.speed_after
    return -(ALPHA * fam["dx"] ** 2 + BETA) * decel - (ETA * ctx.speed_after**2 + LAMBDA) * float(fam["bump"])


# ----------------------------------------------------------------------------- actions, state and baselines
BRAKE_LEVELS = (9.8, 5.9, 2.9, 0.0)  # m/s^2, the paper's four actions


def brake_action(index: int) -> np.ndarray:
    """Action ``index`` of Chae's four as our [steer, pedal]: pedal -1..0 asks for 9.8..0 m/s^2 (envs/vehicle.py)."""
    return np.array([0.0, -BRAKE_LEVELS[int(index)] / 9.8], dtype=np.float32)


class PedestrianHistory:
    """Chae's 15-value state: (dx, dy, v) over the last 5 steps, oldest first: the pedestrian's position relative to
    the front bumper and the ego's speed. Noise N(0, ``noise_m``) on dx and dy from the view's own generator
    (``reset(seed)``); before 5 steps exist the first is repeated. Privileged: it reads the simulator, as the
    paper's perception module would deliver it."""

    steps = 5
    dim = 3 * steps

    def __init__(self, noise_m: float = 0.1):
        self.noise_m = float(noise_m)
        self.reset(0)

    def reset(self, seed: int | None = None) -> None:
        self.rng = np.random.default_rng(seed)
        self.history: list[tuple[float, float, float]] = []

    def __call__(self, env) -> np.ndarray:
        front = env.ego.x + env.params.length / 2
        px, py = env.actors.ped_xy[0]
        noise = self.rng.normal(0.0, self.noise_m, 2) if self.noise_m > 0 else np.zeros(2)
        self.history.append((px - front + noise[0], py - env.ego.y + noise[1], env.ego.v))
        past = self.history[-self.steps :]
        past = [past[0]] * (self.steps - len(past)) + past
        return np.asarray(past, dtype=np.float32).ravel()


class LatestSafeBraking:
    """Privileged baseline: coast until braking fully is the last chance to stop before the safety line of a
    crossing pedestrian (it decides once per step, so it allows one step of travel), then brake fully. It never
    brakes for a pedestrian who stays (Scenario 2). ``bind(env)`` after each reset, as evaluation does."""

    name = "latest_safe_braking"

    def __init__(self, margin_m: float = 0.2):
        self.margin_m = float(margin_m)
        self.env = None
        self.braking = False

    def reset(self, seed: int | None = None) -> None:
        self.braking = False

    def bind(self, env) -> None:
        self.env = env

    def act(self, obs, info) -> np.ndarray:
        env = self.env
        state = env.family_state
        if not self.braking and state is not None and state.started:
            v, dt = env.ego.v, env.step_s
            gap = state.ped_x - SAFETY_LINE_M - (env.ego.x + env.params.length / 2)
            self.braking = gap <= v * dt + v * v / (2 * BRAKE_LEVELS[0]) + self.margin_m
        return brake_action(0 if self.braking else 3)


class ClosingSpeedBraking:
    """Not privileged: a hand-written rule on exactly the state ``dqn_chae`` sees (:class:`PedestrianHistory`, with
    its noise). It fits a line to the pedestrian's lateral distance |dy| over the last ``readings`` readings and,
    from the first step the pedestrian closes in faster than ``threshold_ms``, brakes fully to a stop; before
    that it does not brake. It shows what the agent's noisy state allows: a needless stop needs a noise excursion
    past the threshold, a late brake a slow detection. ``bind(env)`` after each reset, as evaluation does; the view
    is reseeded by ``reset(seed)`` as the agent's observer is, so both see the same noise on the same trial.
    The default 1.25 m/s was chosen on checkpoint selection's draw (seed 99) from 0.5-2 m/s: 1 m/s stops
    needlessly in 2 %, 1.5 m/s bumps in 0.5 % at TTC 1.5 s, 1.25 m/s in neither (docs/results/chae/README.md)."""

    name = "closing_braking"

    def __init__(self, threshold_ms: float = 1.25, readings: int = 5, noise_m: float = 0.1):
        if not 2 <= int(readings) <= PedestrianHistory.steps:
            raise ValueError(f"readings={readings}: the history holds {PedestrianHistory.steps}; give 2..5")
        if not threshold_ms > 0:
            raise ValueError(f"threshold_ms={threshold_ms}: a closing speed in m/s, > 0")
        self.threshold_ms, self.readings = float(threshold_ms), int(readings)
        self.view = PedestrianHistory(noise_m)
        self.env = None
        self.braking = False

    def reset(self, seed: int | None = None) -> None:
        self.view.reset(seed)
        self.braking = False

    def bind(self, env) -> None:
        self.env = env

    def closing_speed(self, history: np.ndarray) -> float:
        """m/s at which |dy| shrinks over the last ``readings`` readings of a 15-value history (least squares)."""
        lateral = np.abs(np.asarray(history, dtype=np.float64).reshape(-1, 3)[-self.readings :, 1])
        t = np.arange(self.readings) * self.env.step_s
        return float(-np.polyfit(t, lateral, 1)[0])

    def act(self, obs, info) -> np.ndarray:
        history = self.view(self.env)  # one reading per decision, as the agent's observer takes
        self.braking = self.braking or self.closing_speed(history) > self.threshold_ms
        return brake_action(0 if self.braking else 3)


class BrakeAtTrigger:
    """The physics check: full braking from the step after the pedestrian starts (Scenario 2: never)."""

    name = "brake_at_trigger"

    def reset(self, seed: int | None = None) -> None:
        self.env = None

    def bind(self, env) -> None:
        self.env = env

    def act(self, obs, info) -> np.ndarray:
        state = self.env.family_state
        return brake_action(0 if state is not None and state.started else 3)
