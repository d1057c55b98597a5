"""Counterfactual costs of continuous manoeuvres, labelled by re-simulation: what the counterfactual-cost actor's
critic learns (``worldmodel/counterfactual.py``; docs/design.md §5).

A **shift** is one continuous manoeuvre with three parameters: steer ``s`` (wheel units, -1 full left .. 1 full
right), pedal ``p`` and a duration ``hold``. The car steers ``s`` for ``hold`` steps, counter-steers ``-s`` for as
long (so it ends about parallel to the road, shifted sideways, rather than pointing at the kerb), then brakes
straight; the pedal is ``p`` until then. ``s = 0, p = -1`` is straight-line braking.

The policy decides at ``decisions`` points, ``interval`` steps apart, from onset: each decision starts a new
shift that replaces the rest of the previous one, and the last one runs to its end. So a manoeuvre is never open
loop for longer than ``interval`` steps, except the last.

The label of a shift started at decision ``d`` is the exact R2 cost (the sum of injury probabilities still to come)
of the rest of the episode when the shift runs for ``interval`` steps and the best of ``continuations`` (or the
shift itself, run on) takes over at the next decision: the value of the shift under a good second decision. At the
last decision there is no second one, and the label is the shift run to its end. Costs come from the camera-less
planning twin (``UrbanCollisionEnv.snapshot`` / ``restore``), as the planner's and the chooser's do.

numpy and pybullet only, like the rest of ``envs``: the policy that drives a labelled episode is any callable.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from .env import DT, UrbanCollisionEnv
from .privileged import privileged_state

BRAKE = np.array([0.0, -1.0], dtype=np.float32)


@dataclass(frozen=True)
class Shift:
    """Steer ``steer`` for ``hold`` steps, counter-steer as long, then brake straight; pedal ``pedal`` until then.
    With ``release``, the final braking lets go of the pedal once the car stands (a reward that charges braking at
    low speed, as Merola's does, would otherwise charge every step of standing on the brake)."""

    steer: float
    pedal: float
    hold: int
    release: bool = False

    def action(self, k: int, speed: float | None = None) -> np.ndarray:
        """The action ``k`` steps after the shift started, the ego at ``speed`` (m/s; read only with ``release``)."""
        if k < self.hold:
            return np.array([self.steer, self.pedal], dtype=np.float32)
        if k < 2 * self.hold:
            return np.array([-self.steer, self.pedal], dtype=np.float32)
        if self.release and speed is not None and speed <= 0.0:
            return np.zeros(2, dtype=np.float32)
        return BRAKE.copy()

    @property
    def length(self) -> int:
        return 2 * self.hold


@dataclass(frozen=True)
class ShiftSpace:
    """How an actor's output ``u`` in [-1, 1]^3 becomes a ``Shift``: ``u[0]`` is the steer; the pedal is a residual
    on full braking, ``p = clip(-1 + 2 u[1], -1, 1)``, so ``u = 0`` brakes straight (with its last layer at zero
    an untrained actor *is* straight-line braking); ``u[2]`` spans the hold from ``hold_s[0]`` to ``hold_s[1]``."""

    hold_s: tuple[float, float] = (0.15, 0.6)
    step_s: float = DT
    release: bool = False  # every shift's final braking lets go once the car stands (``Shift.release``)

    def __post_init__(self):
        lo, hi = (float(x) for x in self.hold_s)
        if not 0 < lo <= hi:
            raise ValueError(f"shift hold_s={list(self.hold_s)} must be [low, high] with 0 < low <= high (s)")

    def shift(self, u) -> Shift:
        u = np.clip(np.asarray(u, dtype=np.float64).reshape(3), -1.0, 1.0)
        lo, hi = (float(x) for x in self.hold_s)
        hold_s = lo + (hi - lo) * (u[2] + 1.0) / 2.0
        pedal = min(1.0, max(-1.0, -1.0 + 2.0 * float(u[1])))
        return Shift(float(u[0]), pedal, max(1, int(round(hold_s / self.step_s))), self.release)


def decision_steps(decisions: int, interval: int) -> list[int]:
    """The episode steps at which the policy decides: 0, interval, 2 interval, ..."""
    if int(decisions) < 1 or int(interval) < 1:
        raise ValueError(f"decisions={decisions} and interval={interval} must both be >= 1")
    return [d * int(interval) for d in range(int(decisions))]


class _Run:
    """A shift started at episode step ``start`` (the planner's ``plan_cost`` reads ``action(t_step)``)."""

    def __init__(self, shift: Shift, start: int):
        self.shift, self.start = shift, int(start)

    def action(self, t_step: int, speed: float | None = None) -> np.ndarray:
        return self.shift.action(t_step - self.start, speed)


def _run_to_end(twin: UrbanCollisionEnv, run: _Run, bound: float = math.inf, reward: str = "r2") -> float:
    """The cost (minus ``reward``) of the rest of the episode from the twin's present state under ``run``; stops at
    ``bound``."""
    cost, key = 0.0, f"reward_{reward}"
    while True:
        _, _, terminated, truncated, info = twin.step(run.action(twin.t_step, twin.ego.v))
        cost -= info[key]
        if cost >= bound or terminated or truncated:
            return cost


def shift_cost(
    twin: UrbanCollisionEnv,
    snap: dict,
    shift: Shift,
    interval: int | None,
    continuations: Sequence[Shift] = (),
    reward: str = "r2",
) -> tuple[float, bool]:
    """The label of ``shift`` started at the state ``snap``: (cost, minus the registered ``reward``: R2's is the sum
    of injury probabilities, a peer family's its own; whether the path that gives it hits a static object).
    ``interval`` None: the shift runs to its end. Else it runs ``interval`` steps, and the cheapest of running on
    and each of ``continuations`` started there is the label."""
    twin.restore(snap)
    start = twin.t_step
    run = _Run(shift, start)
    if interval is None:
        cost = _run_to_end(twin, run, reward=reward)
        return cost, _static(twin)
    head = 0.0
    for _ in range(int(interval)):
        _, _, terminated, truncated, info = twin.step(run.action(twin.t_step, twin.ego.v))
        head -= info[f"reward_{reward}"]
        if terminated or truncated:
            return head, _static(twin)
    middle = twin.snapshot()
    best = head + _run_to_end(twin, run, reward=reward)
    best_static = _static(twin)
    for other in continuations:
        twin.restore(middle)
        cost = head + _run_to_end(twin, _Run(other, start + int(interval)), best - head, reward)
        if cost < best:
            best, best_static = cost, _static(twin)
    return best, best_static


def _static(twin: UrbanCollisionEnv) -> bool:
    return any(c["kind"] == "static" for c in twin.collisions)


def label_episode(
    env: UrbanCollisionEnv,
    spec,
    policy: ShiftPolicy,
    proposals: Callable[[int, np.ndarray], np.ndarray],
    continuations: Sequence[Shift],
    twin: UrbanCollisionEnv,
    reward: str = "r2",
    frames: bool = True,
    true_state: Callable[[UrbanCollisionEnv], np.ndarray] | None = privileged_state,
) -> dict:
    """Drive scenario ``spec`` with ``policy`` (a ``ShiftPolicy``; straight-line braking decides ``u = 0``), and
    at each of its decisions label the shifts ``proposals(d, u_chosen) -> (N, 3)`` by re-simulation
    (``shift_cost`` of ``reward``). Returns per decision ``t`` (D,), ``u`` (D, N, 3), ``costs`` (D, N), ``static``
    (D, N) int8, ``chosen`` (D, 3), ``view`` (D, ...) when the policy encodes what it sees (its ``x`` there), and
    ``state`` (D, ...), ``true_state(env)`` (by default the camera family's ``envs.privileged``: the hazards, the
    ego, what blocks each escape path; training targets only). With ``frames``, also what the policy did up to its
    last decision: ``seg`` (T, H, W) uint8, ``speed`` (T,) and ``action`` (T, 2), the simulator's actions taken
    after each frame, so that the world model can be fed as a live run feeds it. An episode that ends before the
    last decision has fewer."""
    steps, space = policy.steps, policy.space
    obs, _ = env.reset(options={"scenario": spec})
    policy.reset()
    policy.bind(env)
    segs, speeds, actions = [], [], []
    out = {k: [] for k in ("t", "u", "costs", "static", "chosen", "view", "state")}
    for t in range(steps[-1] + 1):
        if frames:
            segs.append(np.asarray(obs["seg"], np.uint8))
            speeds.append(float(np.asarray(obs["speed"]).reshape(-1)[0]))
        snap = env.snapshot() if t in steps else None
        action = policy.act(obs, None)
        if snap is not None:
            d = steps.index(t)
            chosen = policy.chosen[-1]
            us = np.asarray(proposals(d, chosen), np.float32).reshape(-1, 3)
            interval = None if d == len(steps) - 1 else steps[1] - steps[0]
            labels = [shift_cost(twin, snap, space.shift(u), interval, continuations, reward) for u in us]
            out["t"].append(t)
            out["u"].append(us)
            out["costs"].append([c for c, _ in labels])
            out["static"].append([s for _, s in labels])
            out["chosen"].append(chosen)
            if policy.encode is not None:
                out["view"].append(np.asarray(policy.x, np.float32))
            if true_state is not None:
                out["state"].append(true_state(env))
        actions.append(action)
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            break
    labelled = {
        "t": np.asarray(out["t"], np.int16),
        "u": np.stack(out["u"]).astype(np.float32),
        "costs": np.asarray(out["costs"], np.float32),
        "static": np.asarray(out["static"], np.int8),
        "chosen": np.stack(out["chosen"]).astype(np.float32),
    }
    for key in ("view", "state"):
        if out[key]:
            labelled[key] = np.stack(out[key]).astype(np.float32)
    if frames:
        labelled.update(
            seg=np.stack(segs), speed=np.asarray(speeds, np.float32), action=np.stack(actions).astype(np.float32)
        )
    return labelled


def brake_decision(x, d: int) -> np.ndarray:
    """Straight-line braking as a shift policy's decision: ``u = 0``."""
    return np.zeros(3, np.float32)


class ShiftPolicy:
    """Scripted-policy interface (``reset``, ``act``) for a policy that starts a shift at each of its decisions:
    ``decide(x, d) -> u`` in [-1, 1]^3 (``ShiftSpace``) on ``x = encode(obs)``. Up to the last decision every frame
    is encoded and ``note_action`` told the action taken after it (a learned policy's recurrent view of the world;
    both default to nothing; ``bind_view(env)``, for a view that reads the simulator). ``chosen``: the decisions of
    the episode so far."""

    def __init__(
        self,
        space: ShiftSpace,
        decide: Callable[[object, int], np.ndarray],
        decisions: int,
        interval: int,
        name: str = "shifts",
        encode: Callable[[dict], object] | None = None,
        note_action: Callable[[np.ndarray], None] | None = None,
        reset_view: Callable[[], None] | None = None,
        bind_view: Callable[[UrbanCollisionEnv], None] | None = None,
    ):
        self.space, self.decide, self.name = space, decide, name
        self.bind_view = bind_view
        self.steps = decision_steps(decisions, interval)
        self.encode, self.note_action, self.reset_view = encode, note_action, reset_view
        self.t, self.run, self.x, self.env = 0, None, None, None
        self.chosen: list[np.ndarray] = []

    @classmethod
    def on_view(cls, space: ShiftSpace, decide, decisions: int, interval: int, view, name: str) -> ShiftPolicy:
        """A policy that sees through ``view``: an object with ``encode(obs)``, ``note_action(action)``, ``reset()``,
        ``bind(env)`` and ``needs_camera`` (a peer family's sensor on the episode's env)."""
        policy = cls(
            space,
            decide,
            decisions,
            interval,
            name=name,
            encode=view.encode,
            note_action=view.note_action,
            reset_view=view.reset,
            bind_view=view.bind,
        )
        policy.needs_camera = bool(view.needs_camera)
        return policy

    def reset(self, seed: int | None = None) -> None:
        self.t, self.run, self.chosen = 0, None, []
        if self.reset_view is not None:
            self.reset_view()

    def bind(self, env: UrbanCollisionEnv) -> None:
        """Hand a view that reads the simulator (the true state) the episode's env; keep it for the ego's speed,
        which a shift that lets go of the brake at a standstill reads."""
        self.env = env
        if self.bind_view is not None:
            self.bind_view(env)

    def act(self, obs, info) -> np.ndarray:
        t = self.t
        self.t += 1
        watching = t <= self.steps[-1]
        x = self.encode(obs) if watching and self.encode is not None else obs
        self.x = x  # what it saw last: the labeller keeps it at each decision
        if t in self.steps:
            u = np.asarray(self.decide(x, self.steps.index(t)), np.float32).reshape(3)
            self.chosen.append(u)
            self.run = _Run(self.space.shift(u), t)
        speed = self.env.ego.v if self.env is not None else None
        action = self.run.action(t, speed) if self.run is not None else BRAKE.copy()
        if watching and self.note_action is not None:
            self.note_action(action)
        return action
