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

import numpy as np

from envs.ncap import bank, car_bank, car_points, verdict

from . import artifacts, peers
from .common import make_env, set_threads
from .config import hydra_main, validate
from .policies import env_overrides, porav_policies

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
    from tqdm import tqdm

    typed = validate(cfg)
    set_threads(1)
    takeover = typed.ncap.takeover_ttc_s
    out = artifacts.runs_root(cfg) / ("eval_ncap" if takeover == 1.5 else f"eval_ncap_takeover{takeover:g}")
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    pedestrians, cars = specs_of(typed.ncap)
    porav_step = typed.env.step_s if typed.env.family == "porav" else 1.0 / 15.0
    groups = [("porav", porav_step, porav_policies(cfg), "r2", takeover)]
    # family, step, policies, reward the env reports, takeover TTC (None: from the start, since when to act is theirs)
    groups += [(f, 0.1, peers.peer(f).ncap_policies(cfg), peers.peer(f).NCAP_REWARD, None) for f in peers.REGISTRY]
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


def _key(row) -> str:
    return row["policy"] if not row["policy"].startswith("agent_") else f"{row['policy']}/seed{row['policy_seed']}"


def _label(row) -> str:
    return f"{row['test']} {row['variant']}".strip()


def _mean(values) -> float | None:
    values = list(values)
    return float(np.mean(values)) if values else None


def pct(share: float | None) -> float | None:
    return None if share is None else 100 * share


def summarise(rows: list[dict]) -> dict:
    """Per policy: the pedestrian tests' avoidance, 2015 aim and impact speed; the car tests' avoidance, points and
    relative impact speed; collisions with anything else."""
    out = {"policies": {}}
    for key in dict.fromkeys(_key(r) for r in rows):
        mine = [r for r in rows if _key(r) == key]
        ped = [r for r in mine if r["kind"] == "pedestrian"]
        car = [r for r in mine if r["kind"] == "car"]
        out["policies"][key] = {
            "family": mine[0]["family"],
            "pedestrian_runs": len(ped),
            "pedestrian_avoided_pct": pct(_mean(r["avoided"] for r in ped)),
            "aim_met_pct": pct(_mean(r["verdict"] == "pass" for r in ped)),
            "pedestrian_impact_kmh": _mean(r["impact_kmh"] for r in ped if not r["avoided"]),
            "car_runs": len(car),
            "car_avoided_pct": pct(_mean(r["avoided"] for r in car)),
            "car_points_pct": pct(_mean(r["points"] for r in car)),
            "car_impact_kmh": _mean(r["impact_kmh"] for r in car if not r["avoided"]),
            "other_collisions": int(sum(r["other_collision"] for r in mine)),
            "clean_pct": pct(_mean(r["avoided"] and not r["other_collision"] for r in mine)),
        }
    return out


def _fmt(value, digits: int = 0) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def tables(rows: list[dict], summary: dict) -> str:
    lines = [
        "# Euro NCAP AEB tests (approximate: our reading of the protocol, envs/ncap.py)",
        "",
        f"Paper-family policies take over at TTC {summary['takeover_ttc_s']:g} s (the car holds its speed until "
        "then); the peers' policies drive from the test's start. Pedestrian aim (Euro NCAP 2015): avoid up to "
        "40 km/h, hit below 40 km/h from 40 to 60 km/h. Car points: 1 for avoidance, else by the relative impact "
        "speed (< 5 km/h 1, < 15 0.75, < 30 0.5, < 40 0.25; none at 20 km/h and below), confirmed for "
        "CCRs at 50 km/h and at 20 km/h and below, approximate elsewhere. n/a: the policy does not run these "
        "tests. Other collisions: runs that also hit a parked car, a pole or the street; clean runs: the target "
        "avoided and nothing else hit, over every test the policy ran.",
        "",
        "| policy | family | pedestrian avoided % | aim met % | mean impact, km/h | car avoided % | car points % "
        "| mean relative impact, km/h | other collisions | clean runs % |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for key, s in summary["policies"].items():
        lines.append(
            f"| {key} | {s['family']} | {_fmt(s['pedestrian_avoided_pct'])} | {_fmt(s['aim_met_pct'])} | "
            f"{_fmt(s['pedestrian_impact_kmh'], 1) if s['pedestrian_runs'] else 'n/a'} | "
            f"{_fmt(s['car_avoided_pct'])} | {_fmt(s['car_points_pct'])} | "
            f"{_fmt(s['car_impact_kmh'], 1) if s['car_runs'] else 'n/a'} | {s['other_collisions']} | "
            f"{_fmt(s['clean_pct'])} |"
        )
    lines += [
        "",
        "## Per test and speed: ✓ avoided, else the impact speed in km/h (relative for the car tests; ✗: the "
        "pedestrian aim is missed; *: the car also hit something else)",
        "",
    ]
    for key in summary["policies"]:
        mine = [r for r in rows if _key(r) == key]
        lines += [f"### {key}", ""]
        for kind in ("pedestrian", "car"):
            part = [r for r in mine if r["kind"] == kind]
            if not part:
                continue
            speeds = sorted({r["speed_kmh"] for r in part})
            lines += ["| test | " + " | ".join(f"{v:g}" for v in speeds) + " |", "|---|" + "---:|" * len(speeds)]
            for label in dict.fromkeys(_label(r) for r in part):
                cells = []
                for v in speeds:
                    r = next((r for r in part if _label(r) == label and r["speed_kmh"] == v), None)
                    if r is None:
                        cells.append("")
                        continue
                    cell = "✓" if r["avoided"] else f"{r['impact_kmh']:.0f}"
                    cell += "*" if r["other_collision"] else ""
                    cells.append(cell + (" ✗" if r["verdict"] == "fail" else ""))
                lines.append(f"| {label} | " + " | ".join(cells) + " |")
            lines.append("")
    return "\n".join(lines)


def figure(rows: list[dict], path) -> None:
    """At a glance: per policy, the share of pedestrian and car tests avoided and the car points, as bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary = summarise(rows)["policies"]
    keys = list(summary)
    bars = (
        ("pedestrian_avoided_pct", "pedestrian tests avoided"),
        ("car_avoided_pct", "car tests avoided"),
        ("car_points_pct", "car points (approx.)"),
        ("clean_pct", "clean runs: nothing hit at all"),
    )
    fig, ax = plt.subplots(figsize=(max(7.0, 0.75 * len(keys) + 2.5), 4.2))
    width = 0.8 / len(bars)
    x = np.arange(len(keys))
    for k, (field, label) in enumerate(bars):
        values = [summary[key][field] for key in keys]
        at = x + (k - (len(bars) - 1) / 2) * width
        ax.bar(at, [np.nan if v is None else v for v in values], width, label=label)
        for xi, v in zip(at, values, strict=True):
            if v is None:
                ax.text(xi, 2, "n/a", ha="center", fontsize=6, rotation=90)
    ax.set_xticks(x, keys, rotation=35, ha="right", fontsize=7)
    ax.set_ylim(0, 105)
    ax.set_ylabel("%")
    ax.legend(fontsize=8, loc="lower center", bbox_to_anchor=(0.5, 1.06), ncol=len(bars), frameon=False)
    ax.set_title("Euro NCAP AEB tests (approximate), every policy: higher is better", fontsize=10, pad=24)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


main = hydra_main("ncap")(run)

if __name__ == "__main__":
    main()
