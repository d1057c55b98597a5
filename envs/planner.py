"""The privileged planner (``oracle``): what the physics allows, as a ceiling for the learned policies.

It reads the true simulator state, not the camera. At every decision point it re-simulates a fixed set of
candidate manoeuvres from the present with the real dynamics and collision model (a camera-less twin of the
env, restored from ``UrbanCollisionEnv.snapshot``) to the end of the episode, and commits to the one with the
lowest R2 cost (the sum of injury probabilities still to come). It replans every ``replan_every`` steps and
switches only to a strictly better manoeuvre.

Because the scene is deterministic and straight-line braking is the first candidate, the executed episode never
costs more R2 than braking: at onset the committed plan costs at most what braking costs, and every switch
lowers the exact cost of the rest of the episode. ``tests/test_planner.py`` checks this on a seeded sample.

A manoeuvre is a pedal level held throughout, plus an optional steering profile that starts after a delay:
``swerve`` holds the steer to the end; ``lane_change`` holds it for ``hold`` steps, counter-steers for as long,
then straightens, which moves the car sideways by about a lane without leaving it pointing at the kerb.
Candidates are tried in order of gentleness (braking first) and a rollout stops as soon as its cost reaches
the best so far, or the search stops once some candidate costs nothing, which keeps planning cheap.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .env import DT, UrbanCollisionEnv


@dataclass(frozen=True)
class Manoeuvre:
    pedal: float  # -1 full brake .. 1 full throttle, held throughout
    steer: float = 0.0  # -1 full left .. 1 full right; 0 keeps the wheel straight
    delay: int = 0  # steps before the steering starts
    shape: str = "swerve"  # 'swerve' holds the steer; 'lane_change' steers, counter-steers, straightens
    hold: int = 0  # steps of steering (and then of counter-steering) in a lane change

    def action(self, k: int) -> np.ndarray:
        """The action ``k`` steps after the manoeuvre started."""
        steer = 0.0
        if self.steer and k >= self.delay:
            j = k - self.delay
            if self.shape == "swerve":
                steer = self.steer
            elif j < self.hold:
                steer = self.steer
            elif j < 2 * self.hold:
                steer = -self.steer
        return np.array([steer, self.pedal], dtype=np.float32)


def candidate_manoeuvres(
    pedals: Sequence[float] = (-1.0, -0.5, 0.0, 1.0),
    steers: Sequence[float] = (0.3, 0.6, 1.0),
    delays_s: Sequence[float] = (0.0, 0.2, 0.4),
    lane_change_s: Sequence[float] = (0.3, 0.6),
    sides: Sequence[float] = (1.0, -1.0),
    step_s: float = DT,
) -> list[Manoeuvre]:
    """Every combination, gentlest first: straight-line braking, the other straight pedals, then steering
    manoeuvres by increasing steer, later starts before earlier ones. ``sides``: the steering directions tried, in
    order (1 right, -1 left); one side only makes a teacher whose choices a camera student can tell apart.
    Durations are in seconds, turned into steps of ``step_s`` (the env's ``step_s``)."""
    if not pedals or -1.0 not in [float(p) for p in pedals]:
        raise ValueError("planner pedals must include -1.0 (full brake): straight-line braking is its floor")
    for name, values, lo, hi in (("pedals", pedals, -1.0, 1.0), ("steers", steers, 0.0, 1.0)):
        if any(not lo <= float(v) <= hi for v in values):
            raise ValueError(f"planner {name}={list(values)} must lie in [{lo}, {hi}]")
    if any(float(d) < 0 for d in delays_s) or any(float(h) <= 0 for h in lane_change_s):
        raise ValueError("planner delays_s must be >= 0 and lane_change_s > 0")
    if not sides or any(float(x) not in (1.0, -1.0) for x in sides) or len(set(sides)) != len(sides):
        raise ValueError(f"planner sides={list(sides)} must be distinct values of 1.0 (right) and -1.0 (left)")
    pedals = sorted({float(p) for p in pedals}, key=lambda p: (p != -1.0, abs(p + 1.0)))
    out = [Manoeuvre(p) for p in pedals]
    steps = lambda s: int(round(float(s) / step_s))  # noqa: E731
    shapes = [("swerve", 0)] + [("lane_change", max(1, steps(h))) for h in lane_change_s]
    for steer in sorted({float(s) for s in steers if float(s) > 0}):
        for delay in sorted({steps(d) for d in delays_s}, reverse=True):
            for shape, hold in shapes:
                for p in pedals:
                    for sign in sides:
                        out.append(Manoeuvre(p, float(sign) * steer, delay, shape, hold))
    return out


class _Plan:
    """A manoeuvre started at episode step ``start``."""

    def __init__(self, manoeuvre: Manoeuvre, start: int):
        self.manoeuvre, self.start = manoeuvre, start

    def action(self, t_step: int) -> np.ndarray:
        return self.manoeuvre.action(t_step - self.start)


def plan_cost(
    twin: UrbanCollisionEnv,
    snap: dict,
    plan: _Plan,
    bound: float = math.inf,
    reward: str = "r2",
    trace: list | None = None,
    keep: dict | None = None,
    start: tuple[list, dict] | None = None,
) -> float:
    """The cost (minus the registered ``reward``; R2: the sum of injury probabilities) of the rest of the episode
    from ``snap`` under ``plan``, simulated on the camera-less ``twin``; stops early once it reaches ``bound``.
    ``trace``: a list that receives each step's reward. ``keep``: step counts -> None; after that many steps the
    twin's snapshot is stored there (a rollout that ends or is cut short first stores none). ``start``: the rewards
    and the twin's snapshot after the first steps of a rollout with the same actions from ``snap`` (a ``keep`` of
    an earlier call): those steps are summed and checked against the bound as if simulated, then the rollout goes on
    from the snapshot, so the cost is the same float."""
    trace = [] if trace is None else trace
    cost = 0.0
    key = f"reward_{reward}"
    if start is not None:
        rewards, resume_from = start
        for r in rewards:
            trace.append(r)
            cost -= r
            if cost >= bound:
                return cost
        twin.restore(resume_from)
    else:
        twin.restore(snap)
    while True:
        _, _, terminated, truncated, info = twin.step(plan.action(twin.t_step))
        trace.append(info[key])
        cost -= info[key]
        if cost >= bound or terminated or truncated:
            return cost
        if keep is not None and len(trace) in keep:
            keep[len(trace)] = twin.snapshot()


def cost_of_rest(trace: Sequence[float], done: int) -> float:
    """What ``plan_cost`` returns for a plan's rollout restarted ``done`` steps into its ``trace`` (a rollout that
    ran to the episode's end): the same rewards summed in the same order, so the same float."""
    cost = 0.0
    for r in trace[done:]:
        cost -= r
    return cost


class PrivilegedPlanner:
    """Scripted-policy interface (``reset``, ``act``) plus ``bind(env)``, which evaluation calls after each reset
    so the planner can read the true state. ``replan_every``: steps between decisions (1 = every step).
    ``brake_first``: steps of straight-line braking before the planner takes over, the perception ceiling of a
    camera policy that needs that many frames to see the hazard (0 = plan from the first frame).
    ``brake_until_pixels``: K > 0 brakes straight until the hazard participants cover at least K pixels of the
    camera frame (``UrbanCollisionEnv.hazard_pixels``), then plans, replanning every ``replan_every`` steps counted
    from that frame, and keeps planning even if the hazard leaves the frame again: the cap on a policy that acts on
    the camera, named ``oracle_pixelsK``. It needs the env's camera (``bind`` refuses a camera-less env), and in a
    scenario whose hazard never covers K pixels (or that has none) it brakes throughout (0 = off). ``reward``: the
    registered reward whose negative it minimises (R2, or e.g. Kim's ISS, under which every crash costs at least
    e^alpha, so avoiding comes first). Other arguments: ``candidate_manoeuvres``."""

    name = "oracle"

    def __init__(
        self,
        replan_every: int = 3,
        brake_first: int = 0,
        step_s: float = DT,
        reward: str = "r2",
        brake_until_pixels: int = 0,
        **candidates,
    ):
        if int(replan_every) < 1:
            raise ValueError(f"planner replan_every={replan_every} must be >= 1 step")
        if int(brake_first) < 0:
            raise ValueError(f"planner brake_first={brake_first} must be >= 0 steps")
        if int(brake_until_pixels) < 0:
            raise ValueError(f"planner brake_until_pixels={brake_until_pixels} must be >= 0 pixels")
        self.replan_every, self.brake_first = int(replan_every), int(brake_first)
        self.brake_until_pixels = int(brake_until_pixels)
        if self.brake_until_pixels:
            self.name = f"oracle_pixels{self.brake_until_pixels}"
        self.step_s = float(step_s)
        self.reward = reward
        self.candidates = candidate_manoeuvres(step_s=self.step_s, **candidates)
        self.env: UrbanCollisionEnv | None = None
        self._twin: UrbanCollisionEnv | None = None
        self.plan: _Plan | None = None
        self._trace: tuple[int, list] = (0, [])
        self._delays = sorted({m.delay for m in self.candidates if m.steer and m.delay})
        self.seen_at: int | None = None  # the step the hazard first covered brake_until_pixels pixels
        self.rollouts = 0

    @property
    def needs_camera(self) -> bool:
        """Whether it reads the rendered frame (``brake_until_pixels``); evaluation turns the camera on for it."""
        return self.brake_until_pixels > 0

    @classmethod
    def from_settings(
        cls,
        replan_every_s: float,
        brake_first: int = 0,
        step_s: float = DT,
        reward: str = "r2",
        brake_until_pixels: int = 0,
        **candidates,
    ) -> PrivilegedPlanner:
        """From the config's units: ``replan_every_s`` in seconds, ``step_s`` the env's step (``env.step_s``), the
        rest as ``candidate_manoeuvres``."""
        replan = max(1, round(float(replan_every_s) / float(step_s)))
        return cls(
            replan_every=replan,
            brake_first=brake_first,
            step_s=step_s,
            reward=reward,
            brake_until_pixels=brake_until_pixels,
            **candidates,
        )

    def reset(self, seed: int | None = None) -> None:
        self.plan = None
        self._trace: tuple[int, list] = (0, [])  # the step the committed plan was chosen, and its rollout's rewards
        self.seen_at = None

    def bind(self, env: UrbanCollisionEnv) -> None:
        if env.step_s != self.step_s:
            raise ValueError(
                f"the planner's manoeuvres are in steps of {self.step_s} s but the env steps {env.step_s} s; "
                "build it with step_s=env.step_s"
            )
        if self.needs_camera and not env.camera:
            raise ValueError(
                f"{self.name} waits for the hazard to cover {self.brake_until_pixels} px of the camera frame: "
                "bind it to an env with camera=True (without one it would only ever brake)"
            )
        self.env = env
        if self._twin is None:
            self._twin = env.planning_twin()

    def act(self, obs, info) -> np.ndarray:
        if self.env is None:
            raise RuntimeError("PrivilegedPlanner reads the simulator state: call bind(env) after each reset")
        t = self.env.t_step
        if t < self.brake_first:
            return np.array([0.0, -1.0], dtype=np.float32)
        origin = 0
        if self.brake_until_pixels:
            if self.seen_at is None:
                if self.env.hazard_pixels() < self.brake_until_pixels:
                    return np.array([0.0, -1.0], dtype=np.float32)
                self.seen_at = t
            origin = self.seen_at
        if self.plan is None or (t - origin) % self.replan_every == 0:
            self._replan(t)
        return self.plan.action(t)

    def _cost(self, snap: dict, plan: _Plan, bound: float, trace: list, **shared) -> float:
        self.rollouts += 1
        return plan_cost(self._twin, snap, plan, bound, self.reward, trace, **shared)

    def _replan(self, t: int) -> None:
        """Commit to the cheapest candidate started now, or keep the committed plan unless one is strictly cheaper.

        Two rollouts are not simulated again, with the same floats as if they were: the committed plan's cost from
        here is read from the rollout that chose it (the env has since followed that rollout exactly, the scene being
        deterministic), and a steering manoeuvre that starts after a delay continues the straight rollout with its
        pedal from that delay (their actions are the same until then)."""
        snap = self.env.snapshot()
        best, best_cost, best_trace = None, math.inf, []
        if self.plan is not None:
            chosen_at, trace = self._trace
            best, best_trace = self.plan, trace[t - chosen_at :]
            best_cost = cost_of_rest(best_trace, 0)
        straight: dict[tuple[float, int], tuple[list, dict]] = {}  # (pedal, delay) -> its first steps
        for m in self.candidates:
            if best_cost <= 0.0:
                break
            plan, trace = _Plan(m, t), []
            if not m.steer:
                keep = dict.fromkeys(self._delays)
                cost = self._cost(snap, plan, best_cost, trace, keep=keep)
                straight |= {(m.pedal, d): (trace[:d], kept) for d, kept in keep.items() if kept is not None}
            else:
                cost = self._cost(snap, plan, best_cost, trace, start=straight.get((m.pedal, m.delay)))
            if cost < best_cost:  # so its rollout was not cut short by the bound: it ran to the episode's end
                best, best_cost, best_trace = plan, cost, trace
        self.plan, self._trace = best, (t, best_trace)
