"""The Euro NCAP AEB pedestrian bank (``envs/ncap.py``) for every policy of an experiment: one yardstick.

    python -m worldmodel.ncap experiment=NAME [ncap.takeover_ttc_s=1.5]

Runs CPFA-50, CPNA-25, CPNA-75 and CPNC-50 at 20-60 km/h (36 runs, one street layout, deterministic) under every
policy that exists for the experiment:

* the paper's family (0.067 s steps): straight-line braking, the privileged planner, and every trained R1 / R2
  agent (DDPG, chooser). They are built for the last 1.5 s before a crash, so they **take over at TTC
  ``ncap.takeover_ttc_s``** (1.5 s): until then the car holds its speed, and at takeover the policy starts afresh
  (zero LSTM state), as its training episodes did;
* Chae's family (0.1 s steps, from the test's start at TTC 4 s, since deciding when to brake is their job):
  TTC-threshold braking, the privileged latest-safe braking and every ``dqn_chae`` agent.

Writes ``runs/NAME/eval_ncap/`` (``eval_ncap_takeover<T>/`` for another takeover TTC): ``results.csv`` (one row
per run), ``tables.md`` (per policy, per test and speed: avoided, or the impact speed; and Euro NCAP's 2015 aim,
avoid up to 40 km/h and hit below 40 km/h above it, as pass or fail: approximate, not the protocol's scoring
table), ``ncap.png`` (one panel per policy) and ``summary.json`` (last: it marks the run complete).
"""

from __future__ import annotations

import csv
import json
import logging
import math
import time

import numpy as np

from envs.ncap import START_TTC_S, bank, verdict

from . import artifacts
from .common import make_env, set_threads
from .config import hydra_main, validate

log = logging.getLogger(__name__)
HOLD = np.zeros(2, dtype=np.float32)  # no steering, pedal 0: the car holds its speed
COLUMNS = (
    "policy",
    "policy_seed",
    "family",
    "test",
    "speed_kmh",
    "end",
    "avoided",
    "impact_kmh",
    "verdict",
    "pedestrian_injury",
    "vehicle_collision",
    "static_collision",
    "lane_departure",
)


class Takeover:
    """``policy`` in control from step ``start`` on; before it the car holds its speed. The policy is reset (and
    bound to the env) at takeover, so it starts as its episodes did in training."""

    def __init__(self, policy, start: int):
        self.policy, self.start, self.name = policy, int(start), policy.name

    def reset(self, seed=None) -> None:
        self.seed, self.steps, self.env = seed, 0, None

    def bind(self, env) -> None:
        self.env = env

    def act(self, obs, info):
        if self.steps < self.start:
            self.steps += 1
            return HOLD
        if self.steps == self.start:
            self.policy.reset(self.seed)
            bind = getattr(self.policy, "bind", None)
            if bind is not None:
                bind(self.env)
        self.steps += 1
        return self.policy.act(obs, info)


def takeover_step(takeover_ttc_s: float, step_s: float) -> int:
    """The first step at which at most ``takeover_ttc_s`` remain to the nominal impact."""
    return max(0, math.ceil((START_TTC_S - takeover_ttc_s) / step_s - 1e-9))


def porav_policies(cfg):
    """(policy, seed, needs the camera) for the paper's family: braking, the planner, every trained agent."""
    from .policies import policy_for

    names = [p for p in ("braking", "oracle") if p in cfg.evaluate.policies]
    names += [a.key for a in artifacts.trained_agents(cfg)]
    out = []
    for name in names:
        policy, seed, _ = policy_for(cfg, name)
        out.append((policy, seed, name not in ("braking", "oracle")))
    return out


def chae_policies(cfg):
    """(policy, seed, needs the camera) for Chae's family: TTC braking, latest-safe braking, every dqn agent."""
    from .peers import chae

    out = [(chae.TTCBraking(), 0, False), (chae.LatestSafeBraking(), 0, False)]
    for agent in artifacts.trained_agents(cfg, family="chae"):
        policy = chae.load_policy(cfg, agent)
        out.append((policy, agent.seed, policy.see.camera))
    return out


def run_bank(env, policy, specs, family: str, seed: int) -> list[dict]:
    from envs.rollout import rollout

    rows = []
    for spec in specs:
        o = rollout(env, policy, spec).outcome
        hit = bool(o["pedestrian_collision"])
        impact = 3.6 * o["speed_at_collision"] if hit else None
        rows.append(
            {
                "policy": policy.name,
                "policy_seed": seed,
                "family": family,
                "test": spec.test,
                "speed_kmh": spec.speed_kmh,
                "end": o["end"],
                "avoided": int(not hit),
                "impact_kmh": impact if hit else float("nan"),
                "verdict": verdict(spec.speed_kmh, impact),
                "pedestrian_injury": o["pedestrian_injury"],
                "vehicle_collision": o["vehicle_collision"],
                "static_collision": o["static_collision"],
                "lane_departure": o["lane_departure"],
            }
        )
    return rows


def run(cfg) -> dict:
    from tqdm import tqdm

    validate(cfg)
    set_threads(1)
    takeover = float(cfg.ncap.takeover_ttc_s)
    out = artifacts.runs_root(cfg) / ("eval_ncap" if takeover == 1.5 else f"eval_ncap_takeover{takeover:g}")
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    specs = bank(tuple(cfg.ncap.tests), tuple(float(v) for v in cfg.ncap.speeds_kmh))
    porav_step = float(cfg.env.step_s) if cfg.env.family == "porav" else 1.0 / 15.0
    groups = [
        ("porav", porav_step, porav_policies(cfg), "r2", takeover_step(float(cfg.ncap.takeover_ttc_s), porav_step)),
        ("chae", 0.1, chae_policies(cfg), "chae", None),
    ]
    rows: list[dict] = []
    with tqdm(total=len(specs) * sum(len(g[2]) for g in groups), desc="ncap", unit="run") as bar:
        for family, step_s, policies, reward, start in groups:
            envs = {}
            for policy, seed, camera in policies:
                if camera not in envs:
                    envs[camera] = make_env(cfg, camera=camera, family="ncap", step_s=step_s, reward=reward)
                acting = Takeover(policy, start) if start is not None else policy
                rows += run_bank(envs[camera], acting, specs, family, seed)
                bar.update(len(specs))
            for env in envs.values():
                env.close()
    with open(out / "results.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        w.writeheader()
        w.writerows(rows)
    summary = summarise(rows)
    summary["takeover_ttc_s"] = float(cfg.ncap.takeover_ttc_s)
    tests, speeds = list(cfg.ncap.tests), [float(v) for v in cfg.ncap.speeds_kmh]
    (out / "tables.md").write_text(tables(rows, summary, tests, speeds))
    figure(rows, out / "ncap.png", tests, speeds)
    summary["wall_s"] = round(time.perf_counter() - t0, 1)
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    log.info("[ncap] %d runs in %.0f s: %s", len(rows), summary["wall_s"], out / "tables.md")
    return summary


def _key(row) -> str:
    return row["policy"] if not row["policy"].startswith("agent_") else f"{row['policy']}/seed{row['policy_seed']}"


def summarise(rows: list[dict]) -> dict:
    out = {"policies": {}}
    for key in dict.fromkeys(_key(r) for r in rows):
        mine = [r for r in rows if _key(r) == key]
        impacts = [r["impact_kmh"] for r in mine if not r["avoided"]]
        out["policies"][key] = {
            "runs": len(mine),
            "avoided_pct": 100 * float(np.mean([r["avoided"] for r in mine])),
            "aim_met_pct": 100 * float(np.mean([r["verdict"] == "pass" for r in mine])),
            "mean_impact_kmh": float(np.mean(impacts)) if impacts else None,
            "other_collisions": int(sum(r["vehicle_collision"] or r["static_collision"] for r in mine)),
            "family": mine[0]["family"],
        }
    return out


def tables(rows: list[dict], summary: dict, tests: list[str], speeds: list[float]) -> str:
    lines = [
        "# Euro NCAP AEB pedestrian tests (approximate: our reading of the protocol, envs/ncap.py)",
        "",
        f"Paper-family policies take over at TTC {summary['takeover_ttc_s']:g} s (the car holds its speed until "
        "then); Chae-family policies drive from the test's start (TTC 4 s). Aim (Euro NCAP 2015): avoid up to "
        "40 km/h, hit below 40 km/h from 40 to 60 km/h.",
        "",
        "| policy | family | avoided % | aim met % | mean impact speed of the hits, km/h | other collisions |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for key, s in summary["policies"].items():
        impact = "–" if s["mean_impact_kmh"] is None else f"{s['mean_impact_kmh']:.1f}"
        lines.append(
            f"| {key} | {s['family']} | {s['avoided_pct']:.0f} | {s['aim_met_pct']:.0f} | {impact} | "
            f"{s['other_collisions']} |"
        )
    lines += [
        "",
        "## Per test and speed: ✓ avoided, else the impact speed in km/h (✗: the aim is missed; *: the car also hit a "
        "parked car or the street)",
        "",
    ]
    for key in summary["policies"]:
        lines += [f"### {key}", "", "| test | " + " | ".join(f"{v:g}" for v in speeds) + " |"]
        lines.append("|---|" + "---:|" * len(speeds))
        for test in tests:
            cells = []
            for v in speeds:
                r = next(r for r in rows if _key(r) == key and r["test"] == test and r["speed_kmh"] == v)
                cell = "✓" if r["avoided"] else f"{r['impact_kmh']:.0f}"
                cell += "*" if r["vehicle_collision"] or r["static_collision"] else ""
                cells.append(cell + (" ✗" if r["verdict"] == "fail" else ""))
            lines.append(f"| {test} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def figure(rows: list[dict], path, tests: list[str], speeds: list[float]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = list(dict.fromkeys(_key(r) for r in rows))
    cols = min(3, len(keys))
    n_rows = math.ceil(len(keys) / cols)
    fig, axes = plt.subplots(n_rows, cols, figsize=(4.6 * cols + 1.2, 2.3 * n_rows + 0.8), squeeze=False)
    fig.subplots_adjust(left=0.08, right=0.86, wspace=0.45, hspace=0.55, top=0.88)
    image = None
    for ax, key in zip(axes.flat, keys):
        mine = {(r["test"], r["speed_kmh"]): r for r in rows if _key(r) == key}
        grid = np.array([[0.0 if mine[t, v]["avoided"] else mine[t, v]["impact_kmh"] for v in speeds] for t in tests])
        image = ax.imshow(grid, cmap="RdYlGn_r", vmin=0, vmax=60, aspect="auto")
        ax.set_title(key, fontsize=8)
        ax.set_xticks(range(len(speeds)), [f"{v:g}" for v in speeds], fontsize=7)
        ax.set_yticks(range(len(tests)), tests, fontsize=7)
        for i, t in enumerate(tests):
            for j, v in enumerate(speeds):
                r = mine[t, v]
                label = "✓" if r["avoided"] else f"{grid[i, j]:.0f}"
                if r["vehicle_collision"] or r["static_collision"]:
                    label += "*"
                ax.text(j, i, label, ha="center", va="center", fontsize=6)
    for ax in list(axes.flat)[len(keys) :]:
        ax.axis("off")
    fig.suptitle(
        "Euro NCAP pedestrian tests (approximate): impact speed, km/h; ✓ avoided; * hit a parked car or the street; "
        "test speed, km/h, across",
        fontsize=9,
    )
    if image is not None:
        fig.colorbar(image, cax=fig.add_axes([0.89, 0.2, 0.015, 0.6]), label="impact speed, km/h")
    fig.savefig(path, dpi=110)
    plt.close(fig)


main = hydra_main("ncap")(run)

if __name__ == "__main__":
    main()
