"""The report of family chae's evaluation: the summary per policy and run by run against the bars, Table I's
layout and the other tables, the figures and the training curves."""

from __future__ import annotations

import json

import numpy as np

from envs.chae import SAFETY_LINE_M

from ...artifacts import AgentId
from ...stats import wilson

PAPER_TABLE_I = {0.9: 61.29, 1.1: 18.85, 1.3: 0.74}  # bump rate, %; 0 from 1.5 s on (10,000 trials per TTC)
PHYSICS_BAND = {
    0.9: (37.3, 76.5),
    1.1: (3.1, 12.1),
    1.3: (0.0, 0.46),
    1.5: (0.0, 0.0),
}  # brake at the trigger .. 0.1 s late
# What a reproduction must reach (docs/design.md §10): the paper's Table I has no bumps from 1.5 s on, and its
# agent brakes only when it must; we ask for bumps in at most 1 % of the trials at every TTC from 1.5 s and
# needless stops in at most 5 % of Scenario 2's, judged for each run (or ensemble) on its own.
BAR_FROM_TTC, BAR_BUMP, BAR_STOPS = 1.5, 1.0, 5.0
ROLLING = 100


def render_tables(rows: list[dict], settings: dict) -> str:
    """The evaluation's tables from its rows and ``summary["render"]``."""
    return tables(summarise(rows, [float(t) for t in settings["ttcs"]]), int(settings["trials"]))


def _mean(values) -> float | None:
    values = [v for v in values if v == v]
    return float(np.mean(values)) if values else None


def summarise(rows: list[dict], ttcs: list[float]) -> dict:
    """Per policy (seeds pooled): bump, contact, impact speed and injury per TTC, and Scenario 2's stops."""
    out = {"ttcs": ttcs, "policies": {}}
    for policy in dict.fromkeys(r["policy"] for r in rows):
        mine = [r for r in rows if r["policy"] == policy]
        s1 = [r for r in mine if r["scenario"] == 1]
        s2 = [r for r in mine if r["scenario"] == 2]
        s: dict = {"seeds": sorted({r["policy_seed"] for r in mine}), "bump_rate": {}, "contact_rate": {}}
        s["impact_kmh"], s["injury"] = {}, {}
        for ttc in ttcs:
            at = [r for r in s1 if abs(r["ttc"] - ttc) < 1e-9]
            s["bump_rate"][ttc] = 100 * float(np.mean([r["bump"] for r in at]))
            s["contact_rate"][ttc] = 100 * float(np.mean([r["contact"] for r in at]))
            impact = _mean(r["impact_speed"] for r in at)
            s["impact_kmh"][ttc] = None if impact is None else 3.6 * impact
            s["injury"][ttc] = 100 * float(np.mean([r["pedestrian_injury"] for r in at]))
        s["unnecessary_stop_rate"] = 100 * float(np.mean([r["end"] == "stop" for r in s2])) if s2 else None
        s["stop_gaps"] = [r["stop_gap"] for r in s1 if r["stop_gap"] == r["stop_gap"]]
        out["policies"][policy] = s
    out["runs"] = bars_per_run(rows, ttcs)
    return out


def bars_per_run(rows: list[dict], ttcs: list[float]) -> list[dict]:
    """Each (policy, seed) against the bars: its highest bump rate at a TTC from ``BAR_FROM_TTC`` (and where),
    Scenario 2's needless stops, and whether it is inside both. Empty when no TTC reaches ``BAR_FROM_TTC``."""
    late = [t for t in ttcs if t >= BAR_FROM_TTC - 1e-9]
    out = []
    for policy, seed in dict.fromkeys((r["policy"], r["policy_seed"]) for r in rows) if late else ():
        mine = [r for r in rows if r["policy"] == policy and r["policy_seed"] == seed]
        trials = {t: [r["bump"] for r in mine if r["scenario"] == 1 and abs(r["ttc"] - t) < 1e-9] for t in late}
        bumps = {t: 100 * float(np.mean(b)) for t, b in trials.items()}
        worst = max(late, key=lambda t: (bumps[t], -t))  # the earliest of equal rates
        s2 = [r["end"] == "stop" for r in mine if r["scenario"] == 2]
        stops = 100 * float(np.mean(s2)) if s2 else None
        inside = bumps[worst] <= BAR_BUMP and stops is not None and stops <= BAR_STOPS
        out.append(
            {
                "policy": policy,
                "seed": int(seed),
                "max_bump": bumps[worst],
                "at_ttc": worst,
                "max_bump_ci95": list(wilson(int(sum(trials[worst])), len(trials[worst]))),
                "stops": stops,
                "stops_ci95": list(wilson(int(sum(s2)), len(s2))) if s2 else None,
                "inside": bool(inside),
            }
        )
    return out


def tables(summary: dict, trials: int) -> str:
    ttcs = summary["ttcs"]
    head = "| policy | " + " | ".join(f"{t:g}" for t in ttcs) + " |"
    rule = "|---|" + "---:|" * len(ttcs)

    def line(name, values, fmt="{:.1f}"):
        return f"| {name} | " + " | ".join("–" if v is None else fmt.format(v) for v in values) + " |"

    pol = summary["policies"]
    lines = [
        f"# Chae et al. on family chae ({trials} seeded trials per TTC and in Scenario 2; seeds pooled)",
        "",
        "## Table I layout: Scenario 1 bump rate, % (the bumper past the 3 m safety line while the pedestrian crosses)",
        "",
        head,
        rule,
        line("Chae et al. (paper, 10,000 trials)", [PAPER_TABLE_I.get(t, 0.0) for t in ttcs], "{:.2f}"),
        "| physics band (full braking at the trigger .. 0.1 s later) | "
        + " | ".join(f"{PHYSICS_BAND[t][0]:g}–{PHYSICS_BAND[t][1]:g}" if t in PHYSICS_BAND else "0" for t in ttcs)
        + " |",
    ]
    lines += [line(p, [s["bump_rate"][t] for t in ttcs]) for p, s in pol.items()]
    lines += [
        "",
        "## Scenario 2 (the pedestrian stays): unnecessary stops, %",
        "",
        "| policy | stops % |",
        "|---|---:|",
    ]
    lines += [f"| {p} | {s['unnecessary_stop_rate']:.1f} |" for p, s in pol.items()]
    for key, title in (
        ("contact_rate", "footprint contact with the pedestrian, %"),
        ("impact_kmh", "mean impact speed of the contacts, km/h"),
        ("injury", "mean Rosén pedestrian severe-injury risk per trial, %"),
    ):
        lines += ["", f"## Scenario 1: {title}", "", head, rule]
        lines += [line(p, [s[key][t] for t in ttcs]) for p, s in pol.items()]
    if summary.get("runs"):
        lines += [
            "",
            f"## The bars, run by run: bumps <= {BAR_BUMP:g} % at every TTC from {BAR_FROM_TTC:g} s, needless stops "
            f"<= {BAR_STOPS:g} %",
            "",
            f"| policy | seed | highest bump rate from {BAR_FROM_TTC:g} s, % [95 %] (at TTC, s) | needless stops % "
            "[95 %] | inside |",
            "|---|---:|---:|---:|---|",
        ]

        def rate(value, interval):
            return "–" if value is None else f"{value:.1f} [{interval[0]:.1f}, {interval[1]:.1f}]"

        for r in summary["runs"]:
            bump, stops = rate(r["max_bump"], r["max_bump_ci95"]), rate(r["stops"], r["stops_ci95"])
            verdict = "yes" if r["inside"] else "no"
            lines.append(f"| {r['policy']} | {r['seed']} | {bump} ({r['at_ttc']:g}) | {stops} | {verdict} |")
        lines += [
            "",
            "Wilson 95 % intervals; the bars judge the rates themselves. An ensemble's seed is its index: ensemble 0 "
            "of three holds training seeds 0-2, ensemble 1 seeds 3-5, and so on.",
        ]
    lines += [
        "",
        "Stopping distance (Fig. 7 layout): `stopping_distance.png`, the gap from the front bumper to the "
        "pedestrian's line when the car stood still in Scenario 1.",
    ]
    return "\n".join(lines) + "\n"


def figures(rows: list[dict], summary: dict, out) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ttcs = summary["ttcs"]
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(ttcs, [PAPER_TABLE_I.get(t, 0.0) for t in ttcs], "k--", label="Chae et al. (paper)")
    for p, s in summary["policies"].items():
        ax.plot(ttcs, [s["bump_rate"][t] for t in ttcs], marker="o", ms=3, label=p)
    _finish(fig, ax, "TTC at the pedestrian's start, s", "bump rate, %", out / "bump_rate.png")

    fig, ax = plt.subplots(figsize=(7, 4))
    bins = np.arange(0.0, 30.5, 1.0)
    for p, s in summary["policies"].items():
        if s["stop_gaps"]:
            ax.hist(s["stop_gaps"], bins=bins, histtype="step", label=f"{p} ({len(s['stop_gaps'])} stops)")
    ax.axvline(SAFETY_LINE_M, color="r", ls=":", label="safety line (3 m)")
    _finish(
        fig,
        ax,
        "gap from the bumper to the pedestrian's line at standstill, m",
        "Scenario-1 trials",
        out / "stopping_distance.png",
    )


def _finish(fig, ax, xlabel: str, ylabel: str, path) -> None:
    import matplotlib.pyplot as plt

    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def learning_curves(cfg, agents: list[AgentId], path) -> None:
    """Each finished agent's training curve (rolling 100 episodes): bump rate and return, the paper's Fig. 5
    comparison when agents with and without the trauma memory are both there."""
    curves = {}
    for agent in agents:
        metrics = agent.dir(cfg) / "metrics.json"
        if metrics.exists():
            curves[agent.key] = json.loads(metrics.read_text()).get("curve")
    curves = {k: v for k, v in curves.items() if v}
    if not curves:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def rolling(x):
        x = np.asarray(x, float)
        return np.convolve(x, np.ones(ROLLING) / ROLLING, mode="valid") if len(x) >= ROLLING else x

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    for key, curve in curves.items():
        axes[0].plot(100 * rolling([e == "bump" for e in curve["end"]]), label=key, lw=1)
        axes[1].plot(rolling(curve["return"]), label=key, lw=1)
    axes[0].set_title(f"bumps, % of the last {ROLLING} training episodes")
    axes[1].set_title(f"return (Eq. 8), rolling {ROLLING} episodes")
    for ax in axes:
        ax.set_xlabel("episode")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
