"""Kim et al.'s evaluation as Table 2: the per-policy summary with intervals and paired tests, each policy's share
of the achievable avoidance, its markdown tables beside the published ones, and the avoidance figure."""

from __future__ import annotations

import math

import numpy as np

from envs.kim import SCENARIOS

from ...report import share_of_gain
from ...stats import paired_bootstrap_ci, paired_permutation_p, wilson

FLOOR, CEILING = "braking", "oracle"  # 0 % and 100 % of the achievable avoidance: braking, the privileged planner
BOOTSTRAP = 2000  # paired resamples of the trials behind each share's interval, as for the paper's family

# Table 2 (avoidance %, mean injury) per scenario 1 / 2 / 3 / all, as published
PAPER_TABLE_2 = {
    "goal-aware DDPG (paper)": ((82.00, 92.50, 97.00, 92.17), (-1.89, -0.54, -0.43, -0.94)),
    "goal-unaware DDPG (paper)": ((87.00, 89.00, 92.50, 87.83), (-2.66, -0.88, -1.11, -1.52)),
    "human drivers (paper)": ((16.67, 16.67, 0.00, 11.11), (-13.20, -14.21, -13.97, -13.79)),
    "AEB (paper)": ((31.50, 5.30, 0.00, 5.30), (-17.99, -19.22, -21.90, -19.67)),
}


def summarise(rows: list[dict], paper_trials: int) -> dict:
    """Per policy (seeds pooled): avoidance % with its interval and mean injury (-ISS, both units), per scenario
    and overall, on every trial and on the first ``paper_trials`` per scenario."""
    out: dict = {"policies": {}}
    for policy in dict.fromkeys(r["policy"] for r in rows):
        mine = [r for r in rows if r["policy"] == policy]
        s: dict = {"seeds": sorted({r["policy_seed"] for r in mine})}
        for label, subset in (("all", mine), ("paper", [r for r in mine if r["trial"] < paper_trials])):
            cells = {}
            for scenario in (*SCENARIOS, "overall"):
                at = subset if scenario == "overall" else [r for r in subset if r["scenario"] == scenario]
                k, n = sum(r["avoided"] for r in at), len(at)
                cells[scenario] = {
                    "n": n,
                    "avoidance": 100 * k / n if n else None,
                    "interval": wilson(k, n),
                    "injury_kmh": -float(np.mean([r["iss_kmh"] for r in at])) if n else None,
                    "injury_ms": -float(np.mean([r["iss_ms"] for r in at])) if n else None,
                    "rear_ended": 100 * float(np.mean([r["rear_ended"] for r in at])) if n else None,
                }
            s[label] = cells
        out["policies"][policy] = s
    names = list(out["policies"])
    tests = {}
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            ra = sorted(
                (r for r in rows if r["policy"] == a), key=lambda r: (r["policy_seed"], r["scenario"], r["trial"])
            )
            rb = sorted(
                (r for r in rows if r["policy"] == b), key=lambda r: (r["policy_seed"], r["scenario"], r["trial"])
            )
            xa = _per_trial(ra)
            xb = _per_trial(rb)
            keys = sorted(set(xa) & set(xb))
            if keys:
                tests[f"{a} vs {b}"] = paired_permutation_p([xa[k] for k in keys], [xb[k] for k in keys])
    out["paired_p"] = tests
    out["shares"] = achievable_shares(rows)
    return out


def _missed(rows: list[dict], policy: str, seed: int | None = None) -> dict:
    """(scenario, trial) -> the share of ``policy``'s seeds (or of ``seed`` alone) that did not avoid the runner."""
    acc: dict = {}
    for r in rows:
        if r["policy"] == policy and (seed is None or r["policy_seed"] == seed):
            acc.setdefault((r["scenario"], r["trial"]), []).append(1.0 - float(r["avoided"]))
    return {k: float(np.mean(v)) for k, v in acc.items()}


def _share(mine, floor, ceiling, axis=-1):
    """100 (policy - braking) / (planner - braking) of the mean avoidance, as the paper's family computes its share
    on the risk: here on the rate of runners not avoided. NaN where the planner gains under half a point."""
    return share_of_gain(np.mean(floor, axis=axis), np.mean(mine, axis=axis), np.mean(ceiling, axis=axis))


def _finite(x) -> float | None:
    return float(x) if math.isfinite(float(x)) else None


def achievable_shares(rows: list[dict]) -> dict:
    """policy -> its share of the achievable avoidance, 100 (policy - braking) / (planner - braking) of the overall
    avoidance, with a paired-bootstrap 95 % interval over the trials (each resample draws the same trials for the
    policy, braking and the planner; a policy's seeds are averaged per trial) and each seed's share on its own rows.
    Empty without braking and the planner on the same trials."""
    floor, ceiling = _missed(rows, FLOOR), _missed(rows, CEILING)
    out: dict = {}
    for policy in dict.fromkeys(r["policy"] for r in rows):
        mine = _missed(rows, policy)
        keys = sorted(set(mine) & set(floor) & set(ceiling))
        if not keys:
            continue
        samples = [np.array([d[k] for k in keys]) for d in (mine, floor, ceiling)]
        point = _finite(_share(*samples))
        interval = paired_bootstrap_ci(samples, _share, BOOTSTRAP, seed=0) if point is not None else (math.nan,) * 2
        seeds = sorted({r["policy_seed"] for r in rows if r["policy"] == policy})
        by_seed = {}
        for seed in seeds if len(seeds) > 1 else ():
            own = _missed(rows, policy, seed)
            common = sorted(set(own) & set(floor) & set(ceiling))
            by_seed[seed] = _finite(_share(*(np.array([d[k] for k in common]) for d in (own, floor, ceiling))))
        out[policy] = {
            "trials": len(keys),
            "gain_pts": 100.0 * float(np.mean(samples[1]) - np.mean(samples[2])),
            "share": point,
            "interval": [_finite(x) for x in interval],
            "by_seed": by_seed,
        }
    return out


def _per_trial(rows: list[dict]) -> dict:
    """Mean ISS (km/h) per (scenario, trial), over a policy's seeds."""
    acc: dict = {}
    for r in rows:
        acc.setdefault((r["scenario"], r["trial"]), []).append(r["iss_kmh"])
    return {k: float(np.mean(v)) for k, v in acc.items()}


def tables(summary: dict, trials: int, paper_trials: int) -> str:
    pol = summary["policies"]
    head = "| policy | right | left | left turn | overall | right | left | left turn | overall |"
    rule = "|---|" + "---:|" * 8

    def fmt(v, f="{:.1f}"):
        return "–" if v is None else f.format(v)

    lines = [
        "# Kim et al. on family kim (seeds pooled): Table 2's layout",
        "",
        f"## The paper's size: the first {paper_trials} trials per scenario",
        "",
        "Avoidance % (no collision of any kind) | mean injury (minus the summed Sobhani ISS per episode, ΔV in km/h)",
        "",
        head,
        rule,
    ]
    for name, (avoid, injury) in PAPER_TABLE_2.items():
        lines.append(f"| {name} | " + " | ".join(f"{v:.2f}" for v in (*avoid, *injury)) + " |")
    for name, s in pol.items():
        c = s["paper"]
        cells = [fmt(c[k]["avoidance"]) for k in (*SCENARIOS, "overall")]
        cells += [fmt(c[k]["injury_kmh"], "{:.2f}") for k in (*SCENARIOS, "overall")]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "The paper's inconsistencies (docs/design.md §10): its 'all' column is not the mean of the three scenarios, "
        "and 87.00 / 31.50 / 5.30 are not multiples of 1/30; its human row is a driving-simulator study, not "
        "reproduced here.",
        "",
        f"## {trials} trials per scenario, with 95 % Wilson intervals",
        "",
        "| policy | seeds | right | left | left turn | overall | injury (km/h) | injury (m/s) | rear-ended % |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, s in pol.items():
        c = s["all"]
        cells = [
            f"{c[k]['avoidance']:.1f} [{c[k]['interval'][0]:.0f}, {c[k]['interval'][1]:.0f}]"
            for k in (*SCENARIOS, "overall")
        ]
        o = c["overall"]
        lines.append(
            f"| {name} | {','.join(map(str, s['seeds']))} | "
            + " | ".join(cells)
            + f" | {o['injury_kmh']:.2f} | {o['injury_ms']:.2f} | {o['rear_ended']:.1f} |"
        )
    lines += _share_lines(summary.get("shares", {}), pol)
    lines += ["", "## Pairwise tests (paired sign-flip permutation test on per-trial ISS, 10,000 flips)", ""]
    lines += ["| pair | p |", "|---|---:|"]
    lines += [f"| {pair} | {p:.4f} |" for pair, p in summary["paired_p"].items()]
    lines.append("")
    return "\n".join(lines)


def _share_lines(shares: dict, pol: dict) -> list[str]:
    if not shares:
        return ["", "No share of the achievable avoidance: it needs braking and the planner (oracle) on the trials."]
    gain = next(iter(shares.values()))["gain_pts"]
    lines = [
        "",
        "## Share of the achievable avoidance",
        "",
        f"100 × (policy − braking) / (planner − braking) of the overall avoidance: 0 is braking, 100 the privileged "
        f"planner, which avoids {gain:.1f} points more than braking here. 95 % paired-bootstrap interval over the "
        f"trials ({BOOTSTRAP:,} resamples drawing the same trials for the policy, braking and the planner; a policy's "
        "seeds averaged per trial); each seed's share from its own rows.",
        "",
        "| policy | seeds | avoided % | share % [95 %] | each seed's share % |",
        "|---|---|---:|---:|---:|",
    ]

    def fmt(v):
        return "–" if v is None else f"{v:.1f}"

    for name, s in shares.items():
        low, high = s["interval"]
        interval = "" if low is None or high is None else f" [{low:.1f}, {high:.1f}]"
        seeds = " / ".join(fmt(v) for v in s["by_seed"].values()) or "–"
        avoided = pol[name]["all"]["overall"]["avoidance"]
        lines.append(
            f"| {name} | {','.join(map(str, pol[name]['seeds']))} | {avoided:.1f} | {fmt(s['share'])}{interval} | "
            f"{seeds} |"
        )
    return lines


def figure(summary: dict, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pol = summary["policies"]
    names = list(pol)
    groups = (*SCENARIOS, "overall")
    fig, ax = plt.subplots(figsize=(8, 3.6))
    width = 0.8 / max(1, len(names))
    for i, name in enumerate(names):
        c = pol[name]["all"]
        vals = [c[g]["avoidance"] for g in groups]
        lo = [v - c[g]["interval"][0] for g, v in zip(groups, vals, strict=True)]
        hi = [c[g]["interval"][1] - v for g, v in zip(groups, vals, strict=True)]
        ax.bar(np.arange(len(groups)) + i * width, vals, width, yerr=[lo, hi], capsize=2, label=name)
    ax.set_xticks(np.arange(len(groups)) + 0.4 - width / 2, [g.replace("_", " ") for g in groups])
    ax.set_ylabel("runner avoided, no collision (%)")
    ax.set_ylim(0, 105)
    ax.axhline(87.83, color="k", ls=":", lw=1)
    ax.text(len(groups) - 0.5, 88.5, "paper's goal-unaware DDPG, overall", ha="right", fontsize=7)
    ax.legend(fontsize=7, ncol=2, loc="lower left")
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def render_tables(rows: list[dict], settings: dict) -> str:
    """The evaluation's tables from its rows and ``summary["render"]``."""
    paper_trials = int(settings["paper_trials"])
    return tables(summarise(rows, paper_trials), int(settings["trials"]), paper_trials)
