"""Brake, and switch once to a manoeuvre predicted to cost less: the decision structure of the chooser agent.

Students that clone the planner's *actions* fail where the camera cannot tell the planner's reasons
apart: least squares averages a swerve left and a swerve right into braking straight, or into a half-swerve. The
chooser learns the *costs* of a fixed set of manoeuvres instead (docs/design.md §5):

* It brakes straight from onset, and at each of its first ``decide_steps`` steps it asks a scorer for the R2 cost
  (the sum of injury probabilities still to come) of starting each candidate manoeuvre now and holding it to the
  end. ``candidates[0]`` is straight-line braking.
* When the cheapest candidate beats braking by more than ``margin``, and braking itself is predicted to cost more
  than ``min_brake_cost`` when that is set (where braking is nearly safe a switch has little to win and a wrong one
  much to lose), it commits to it and follows it open loop.

With the exact costs (``ExactCosts``, which reads the true state like the planner) this is a privileged policy whose
result bounds what a learned scorer can reach with the same candidates. A learned scorer trained by least squares
on exact costs predicts their expectation given what it sees, and the lowest expected cost is the right choice under
that uncertainty: the averaging that spoils action cloning is here what the decision needs.

Before committing the chooser always brakes, so the states it decides in are exactly those of straight-line
braking: ``cost_labels`` records them with their exact costs, and a scorer trained on them sees at test time the
distribution it was trained on (no DAgger needed).

numpy and pybullet only, like the rest of ``envs``: the learned scorer is any callable.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from .env import DT, UrbanCollisionEnv
from .planner import Manoeuvre, _Plan, plan_cost

BRAKE = np.array([0.0, -1.0], dtype=np.float32)


def chooser_candidates(
    steers: Sequence[float] = (0.3, 1.0),
    lane_change_s: Sequence[float] = (0.3, 0.6),
    pedals: Sequence[float] = (-1.0,),
    sides: Sequence[float] = (1.0, -1.0),
    swerve: bool = True,
    step_s: float = DT,
) -> list[Manoeuvre]:
    """Straight-line braking first, then every steer × shape (held swerve if ``swerve``, lane changes) × pedal ×
    side, started now. No delayed starts: the chooser decides again at the next step, so waiting is a choice."""
    if not steers or any(not 0.0 < float(s) <= 1.0 for s in steers):
        raise ValueError(f"chooser steers={list(steers)} must lie in (0, 1]")
    if any(not -1.0 <= float(p) <= 1.0 for p in pedals) or not pedals:
        raise ValueError(f"chooser pedals={list(pedals)} must lie in [-1, 1]")
    if any(float(h) <= 0 for h in lane_change_s):
        raise ValueError(f"chooser lane_change_s={list(lane_change_s)} must be > 0")
    if not sides or any(float(x) not in (1.0, -1.0) for x in sides) or len(set(sides)) != len(sides):
        raise ValueError(f"chooser sides={list(sides)} must be distinct values of 1.0 (right) and -1.0 (left)")
    if not swerve and not lane_change_s:
        raise ValueError("the chooser needs a manoeuvre besides braking: lane_change_s or swerve")
    shapes = [("swerve", 0)] if swerve else []
    shapes += [("lane_change", max(1, int(round(float(h) / step_s)))) for h in lane_change_s]
    out = [Manoeuvre(-1.0)]
    for steer in sorted({float(s) for s in steers}):
        for shape, hold in shapes:
            for pedal in pedals:
                for side in sides:
                    out.append(Manoeuvre(float(pedal), float(side) * steer, 0, shape, hold))
    return out


def decide_steps_for(decide_s: float, step_s: float = DT) -> int:
    if not decide_s > 0:
        raise ValueError(f"chooser decide_s={decide_s} must be > 0")
    return max(1, int(math.ceil(float(decide_s) / step_s - 1e-9)))


class ExactCosts:
    """The privileged scorer: the exact cost of each candidate from the true state (``bind(env)`` after reset)."""

    def __init__(self, candidates: Sequence[Manoeuvre]):
        self.candidates = list(candidates)
        self.env: UrbanCollisionEnv | None = None
        self._twin: UrbanCollisionEnv | None = None

    def bind(self, env: UrbanCollisionEnv) -> None:
        self.env = env
        if self._twin is None:
            self._twin = env.planning_twin()

    def __call__(self, obs=None, t: int | None = None) -> np.ndarray:
        if self.env is None:
            raise RuntimeError("ExactCosts reads the simulator state: call bind(env) after each reset")
        snap, t_step = self.env.snapshot(), self.env.t_step
        return np.array([plan_cost(self._twin, snap, _Plan(m, t_step)) for m in self.candidates], np.float64)


def switch_choice(cost: np.ndarray, margin: float, min_brake_cost: float = 0.0) -> int | None:
    """The candidate the chooser commits to on these predicted costs, or None to keep braking: the cheapest, when it
    beats braking (``cost[0]``) by more than ``margin`` and, if ``min_brake_cost`` is set, braking is predicted to
    cost more than that. The one rule of the live chooser and of ``worldmodel.chooser.policy_cost``."""
    k = int(np.argmin(cost))
    nearly_safe = min_brake_cost > 0 and cost[0] <= min_brake_cost  # 0: no floor at all
    return k if cost[0] - cost[k] > margin and not nearly_safe else None


class ManoeuvreChooser:
    """Scripted-policy interface (``reset``, ``act``; ``bind`` when the scorer reads the true state).

    ``scores(obs, t) -> (len(candidates),)`` predicted costs at decision step ``t`` (0 at onset); ``reset_scorer``
    is called at every reset (a learned scorer's recurrent state). ``env_overrides``: env settings the scores need
    (a scorer that reads the narrow second camera: ``{"tele_fov_deg": 30.0}``), for whoever makes its env."""

    def __init__(
        self,
        candidates: Sequence[Manoeuvre],
        scores: Callable[[dict, int], np.ndarray],
        decide_steps: int,
        margin: float = 0.0,
        name: str = "chooser",
        min_brake_cost: float = 0.0,
        reset_scorer: Callable[[], None] | None = None,
        note_action: Callable[[np.ndarray], None] | None = None,
        env_overrides: dict | None = None,
    ):
        self.candidates = list(candidates)
        if not self.candidates or self.candidates[0] != Manoeuvre(-1.0):
            raise ValueError("the chooser's first candidate must be straight-line braking, Manoeuvre(-1.0)")
        if int(decide_steps) < 1 or not margin >= 0 or not min_brake_cost >= 0:
            raise ValueError(
                f"chooser decide_steps={decide_steps} must be >= 1, margin={margin} and "
                f"min_brake_cost={min_brake_cost} >= 0"
            )
        self.scores, self.decide_steps, self.margin, self.name = scores, int(decide_steps), float(margin), name
        self.min_brake_cost = float(min_brake_cost)
        self.reset_scorer, self.note_action = reset_scorer, note_action
        self.env_overrides = dict(env_overrides or {})
        self.plan: _Plan | None = None
        self.t = 0
        self.choice: int | None = None  # the candidate committed to (None: braked throughout)

    def reset(self, seed: int | None = None) -> None:
        self.plan, self.t, self.choice = None, 0, None
        if self.reset_scorer is not None:
            self.reset_scorer()

    def bind(self, env: UrbanCollisionEnv) -> None:
        bind = getattr(self.scores, "bind", None)
        if bind is not None:
            bind(env)

    def act(self, obs, info) -> np.ndarray:
        t = self.t
        self.t += 1
        if self.plan is None and t < self.decide_steps:
            cost = np.asarray(self.scores(obs, t), dtype=np.float64)
            k = switch_choice(cost, self.margin, self.min_brake_cost)
            if k is not None:
                self.plan, self.choice = _Plan(self.candidates[k], t), k
        action = BRAKE.copy() if self.plan is None else self.plan.action(t)
        if self.note_action is not None:
            self.note_action(action)
        return action


HAZARD_STATE = ("pedestrian", "ped_dx", "ped_dy", "ped_vx", "ped_vy", "car", "car_dx", "car_dy", "car_vx", "car_vy")


def hazard_state(env: UrbanCollisionEnv) -> np.ndarray:
    """The privileged facts a camera student should perceive (``HAZARD_STATE``): whether the hazard pedestrian and
    the hazard car are there, and their position relative to the ego (m) and velocity (m/s), zeros when absent.
    Training targets only: the chooser never reads them when it acts."""
    a, e = env.actors, env.ego
    out = np.zeros(len(HAZARD_STATE), np.float32)
    for k, (hazard, active, xy, vel) in enumerate(
        ((a.ped_hazard, a.ped_active, a.ped_xy, a.ped_vel), (a.car_hazard, a.car_active, a.car_xy, a.car_vel))
    ):
        i = np.flatnonzero(hazard & active)
        if len(i):
            out[5 * k : 5 * k + 5] = [1.0, xy[i[0], 0] - e.x, xy[i[0], 1] - e.y, vel[i[0], 0], vel[i[0], 1]]
    return out


def cost_labels(
    env: UrbanCollisionEnv, spec, candidates: Sequence[Manoeuvre], decide_steps: int, twin: UrbanCollisionEnv
) -> dict:
    """Straight-line braking through scenario ``spec``, and at each of its first ``decide_steps`` steps the exact
    cost of starting every candidate there: what the chooser's scorer learns from. Returns ``seg`` (T, H, W) uint8,
    ``speed`` (T,), ``costs`` (T, K), ``static`` (T, K) int8, whether starting that candidate there ends in a
    static object (so a decision rule's static-collision rate is counted offline, as its cost is), and ``state``
    (T, len(HAZARD_STATE)), the privileged facts of ``hazard_state``; with a second, narrow camera
    (``env.tele_fov_deg``) also its frames, ``seg_tele`` (T, H, W)."""
    obs, _ = env.reset(options={"scenario": spec})
    segs, teles, speeds, costs, statics, states = [], [], [], [], [], []
    for t in range(decide_steps):
        snap = env.snapshot()
        states.append(hazard_state(env))
        row_cost, row_static = [], []
        for m in candidates:
            row_cost.append(plan_cost(twin, snap, _Plan(m, t)))
            row_static.append(any(c["kind"] == "static" for c in twin.collisions))
        costs.append(row_cost)
        statics.append(row_static)
        segs.append(np.asarray(obs["seg"], np.uint8))
        if "seg_tele" in obs:
            teles.append(np.asarray(obs["seg_tele"], np.uint8))
        speeds.append(float(np.asarray(obs["speed"]).reshape(-1)[0]))
        obs, _, terminated, truncated, info = env.step(BRAKE)
        if terminated or truncated:
            break
    out = {
        "seg": np.stack(segs),
        "speed": np.asarray(speeds, np.float32),
        "costs": np.asarray(costs, np.float32),
        "static": np.asarray(statics, np.int8),
        "state": np.stack(states),
    }
    if teles:
        out["seg_tele"] = np.stack(teles)
    return out
