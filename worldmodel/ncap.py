"""The Euro NCAP AEB bank (``envs/ncap.py``) for every policy of an experiment: one yardstick.

    python -m worldmodel.ncap experiment=NAME [ncap.takeover_ttc_s=1.5]

Runs the pedestrian tests (CPFA-50, CPNA-25, CPNA-75, CPNC-50 at 20-60 km/h) and the car-to-car rear tests (CCRs,
CCRm at every overlap, CCRb's four variants), on one street layout, deterministic, under every policy that exists
for the experiment, each at its own step length:

* the paper's family (0.067 s steps): straight-line braking, the privileged planner, and every trained R1 / R2
  agent (DDPG, chooser). They are built for the last 1.5 s before a crash, so they **take over at TTC
  ``ncap.takeover_ttc_s``** (1.5 s; for the car tests, the bumper gap over the closing speed): until then the car
  holds its speed, and at takeover the policy starts afresh (zero LSTM state), as its training episodes did;
* Chae's family (0.1 s steps, from the test's start, since deciding when to brake is their job): TTC-threshold
  braking and the privileged latest-safe braking (pedestrian tests only: they brake for a crossing pedestrian),
  and every ``dqn_chae`` agent (its privileged pedestrian-history view: pedestrian tests only);
* Kim's family (0.1 s, from the start): AEB-3m and every goal-unaware ``ddpg_kim`` agent (LIDAR; a goal-aware one
  needs the junction's goal and is left out);
* Merola's family (0.1 s, from the start): every ``ddqn_merola`` agent (camera frames).

Writes ``runs/NAME/eval_ncap/`` (``eval_ncap_takeover<T>/`` for another takeover TTC): ``results.csv`` (one row
per run), ``tables.md`` (the headline per policy; then per policy, per test and speed: avoided, or the impact
speed; pedestrian tests with Euro NCAP's 2015 aim, avoid up to 40 km/h and hit below 40 km/h above it; car tests
with points per impact-speed band, approximate where they are not confirmed, docs/design.md §10), ``ncap.png``
(one panel per policy) and ``summary.json`` (last: it marks the run complete).
"""

from __future__ import annotations

import csv
import json
import logging
import math
import time
from pathlib import Path

import numpy as np

from envs.ncap import bank, car_bank, car_points, verdict

from . import artifacts, registry
from .common import make_env, set_threads, writer_lock
from .config import hydra_main, validate
from .policies import env_overrides
from .report.ncap import figure, summarise, tables

log = logging.getLogger(__name__)
HOLD = np.zeros(2, dtype=np.float32)  # no steering, pedal 0: the car holds its speed
COLUMNS = (
    "policy",
    "policy_seed",
    "family",
    "kind",
    "test",
    "variant",
    "speed_kmh",
    "end",
    "avoided",
    "impact_kmh",
    "verdict",
    "points",
    "points_confirmed",
    "pedestrian_injury",
    "occupant_injury",
    "vehicle_collision",
    "static_collision",
    "other_collision",
    "lane_departure",
)


class Takeover:
    """``policy`` in control once the test's time to collision (``env.family_state.ttc``) has fallen to ``ttc_s``;
    before it the car holds its speed. The policy is reset (and bound to the env) at takeover, so it starts as its
    episodes did in training."""

    def __init__(self, policy, ttc_s: float):
        self.policy, self.ttc_s, self.name = policy, float(ttc_s), policy.name

    def reset(self, seed=None) -> None:
        self.seed, self.started, self.env = seed, False, None

    def bind(self, env) -> None:
        self.env = env

    def act(self, obs, info):
        if not self.started:
            env = self.env
            if env.family_state.ttc(env.t_step * env.step_s, env.ego) > self.ttc_s + 1e-9:
                return HOLD
            self.started = True
            self.policy.reset(self.seed)
            bind = getattr(self.policy, "bind", None)
            if bind is not None:
                bind(env)
        return self.policy.act(obs, info)


def takeover_step(takeover_ttc_s: float, step_s: float) -> int:
    """The first step of a pedestrian test at which at most ``takeover_ttc_s`` remain to the nominal impact."""
    from envs.ncap import START_TTC_S

    return max(0, math.ceil((START_TTC_S - takeover_ttc_s) / step_s - 1e-9))


def run_bank(env, policy, specs, family: str, seed: int) -> list[dict]:
    from envs.rollout import rollout

    rows = []
    for spec in specs:
        o = rollout(env, policy, spec).outcome
        if spec.car_test:
            target = [h for h in env.collisions if h["kind"] == "vehicle" and h["hazard"]]
            hit = bool(target)
            impact = 3.6 * target[0]["relative_speed"] if hit else None
            points, confirmed = car_points(spec.speed_kmh, impact)
            aim = ""
        else:
            hit = bool(o["pedestrian_collision"])
            impact = 3.6 * o["speed_at_collision"] if hit else None
            points, confirmed, aim = math.nan, False, verdict(spec.speed_kmh, impact)
        others = [h for h in env.collisions if not h["hazard"]]
        rows.append(
            {
                "policy": policy.name,
                "policy_seed": seed,
                "family": family,
                "kind": "car" if spec.car_test else "pedestrian",
                "test": spec.test,
                "variant": spec.variant,
                "speed_kmh": spec.speed_kmh,
                "end": o["end"],
                "avoided": int(not hit),
                "impact_kmh": impact if hit else float("nan"),
                "verdict": aim,
                "points": points,
                "points_confirmed": int(confirmed),
                "pedestrian_injury": o["pedestrian_injury"],
                "occupant_injury": o["occupant_injury"],
                "vehicle_collision": o["vehicle_collision"],
                "static_collision": o["static_collision"],
                "other_collision": int(bool(others)),
                "lane_departure": o["lane_departure"],
            }
        )
    return rows


def specs_of(c) -> tuple[list, list]:
    """(pedestrian runs, car-to-car runs) of the typed ``ncap`` section ``c``."""
    pedestrians = bank(tuple(c.tests), tuple(c.speeds_kmh)) if c.tests else []
    cars = car_bank(tuple(c.car_tests), tuple(c.overlaps_pct), c.car_speed_step_kmh)
    return pedestrians, cars


def run(cfg) -> dict:
    typed = validate(cfg)
    takeover = typed.ncap.takeover_ttc_s
    out = artifacts.runs_root(cfg) / ("eval_ncap" if takeover == 1.5 else f"eval_ncap_takeover{takeover:g}")
    with writer_lock(out, "one NCAP evaluation"):
        return _evaluate(cfg, typed, out)


def _evaluate(cfg, typed, out: Path) -> dict:
    from tqdm import tqdm

    set_threads(1)
    takeover = typed.ncap.takeover_ttc_s
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    pedestrians, cars = specs_of(typed.ncap)
    # family, step, policies, reward the env reports, takeover TTC (None: from the start, since when to act is theirs)
    groups = [(name, *registry.system(name).ncap_group(cfg, takeover)) for name in registry.names()]
    total = sum(len(pedestrians) + (len(cars) if both else 0) for g in groups for _, _, _, both in g[2])
    rows: list[dict] = []
    with tqdm(total=total, desc="ncap", unit="run") as bar:
        for family, step_s, policies, reward, start in groups:
            envs = {}
            for policy, seed, camera, car_tests in policies:
                extra = env_overrides(policy)
                key = (camera, *sorted(extra.items()))
                if key not in envs:
                    envs[key] = make_env(cfg, camera=camera, family="ncap", step_s=step_s, reward=reward, **extra)
                acting = Takeover(policy, start) if start is not None else policy
                specs = pedestrians + (cars if car_tests else [])
                rows += run_bank(envs[key], acting, specs, family, seed)
                bar.update(len(specs))
            for env in envs.values():
                env.close()
    with open(out / "results.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        w.writeheader()
        w.writerows(rows)
    summary = summarise(rows)
    summary["takeover_ttc_s"] = takeover
    summary["render"] = {"takeover_ttc_s": takeover}  # what tables() is given beside the rows
    (out / "tables.md").write_text(tables(rows, summary))
    figure(rows, out / "ncap.png")
    summary["wall_s"] = round(time.perf_counter() - t0, 1)
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    log.info("[ncap] %d runs in %.0f s: %s", len(rows), summary["wall_s"], out / "tables.md")
    return summary


main = hydra_main("ncap")(run)

if __name__ == "__main__":
    main()
