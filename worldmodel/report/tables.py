"""The paper's Tables I-III laid out with our numbers beside the published ones, Table IV (the share of the
achievable improvement), and the secondary tables, as Markdown."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

from .rows import _fmt_speed, _fmt_ttc, _involves, _mean, grid_of, policy_label, policy_order
from .summary import (
    CEILING,
    MIN_ACHIEVABLE_GAIN,
    _group,
    _metric_grid,
    achievable_share_grids,
    cells_above_baseline,
    overall_achievable_share,
    seed_spread,
)

# ----------------------------------------------------------------------------- the paper's numbers
# Porav & Newman 2018, Tables I and II (CARLA): values in %, kept as the paper prints them.
_PAPER_TTCS = (0.5, 0.75, 1.0, 1.5)
_PAPER_SPEEDS = (10.0, 20.0, 30.0)


def _paper_table(values: dict[str, str]) -> dict[str, dict[tuple[float, float], str]]:
    out = {}
    for policy, text in values.items():
        cells = text.split()
        assert len(cells) == len(_PAPER_TTCS) * len(_PAPER_SPEEDS)
        keys = [(t, s) for t in _PAPER_TTCS for s in _PAPER_SPEEDS]
        out[policy] = dict(zip(keys, cells))
    return out


PAPER_TABLE_I = _paper_table(
    {
        "braking": "0.886 5.40 6.08  0.263 0.360 1.650  0.015 0.064 0.828  0.0 0.0 0.0",
        "agent_r1": "0.168 2.462 2.860  0.0 0.189 1.799  0.0 0.0 0.0  0.0 0.0 0.0",
        "agent_r2": "0.054 1.087 3.487  0.0 0.172 1.633  0.0 0.0 0.0  0.0 0.0 0.0",
    }
)
PAPER_TABLE_II = _paper_table(
    {
        "braking": "0.0 0.372 0.829  0.008 0.603 1.240  0.006 0.042 0.015  0.001 0.002 0.245",
        "agent_r1": "0.001 0.467 0.579  0.001 0.754 0.495  0.0 0.052 0.001  0.0 0.0 0.0",
        "agent_r2": "0.0 0.001 0.663  0.0 0.124 0.0  0.0 0.0158 0.0  0.0 0.0 0.0",
    }
)
# Table III: pedestrian collision rate (%) by TTC.
PAPER_TABLE_III = {
    "Porav & Newman R2 (paper)": {0.5: "21.8", 0.75: "5.0", 0.9: "1.4", 1.1: "0.0", 1.3: "0.0", 1.5: "0.0"},
    "Chae et al. (paper)": {0.5: "NA", 0.75: "NA", 0.9: "61.29", 1.1: "18.85", 1.3: "0.74", 1.5: "0.0"},
}

MISSING = "—"


# ----------------------------------------------------------------------------- tables (Tables I–III)
def _md_row(cells: Sequence[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def _fmt(v: float, digits: int) -> str:
    return MISSING if v is None or not math.isfinite(v) else f"{v:.{digits}f}"


def _count_note(counts: Iterable[int], what: str) -> str:
    counts = sorted({c for c in counts if c > 0})
    if not counts:
        return f"_No scenarios with {what} in this grid._"
    if len(counts) == 1:
        return f"_Each cell averages {counts[0]} scenario{'s' if counts[0] != 1 else ''} ({what}) per policy._"
    return f"_Each cell averages between {counts[0]} and {counts[-1]} scenarios ({what}) per policy._"


def _ttc_speed_table(rows, column: str, who: str, reference: dict, title: str, what: str, notes: list[str]) -> str:
    grid = grid_of(rows)
    ttcs, speeds = grid["ttcs"], grid["speeds"]
    policies = policy_order(rows)
    lines = [f"### {title}", ""]
    header = ["Policy type"]
    for t in ttcs:
        header += [f"TTC {_fmt_ttc(t)} s"] + [""] * (len(speeds) - 1)
    lines.append(_md_row(header))
    lines.append(_md_row(["---"] + ["---:"] * (len(ttcs) * len(speeds))))
    lines.append(_md_row(["*speed (m/s)*"] + [_fmt_speed(s) for _ in ttcs for s in speeds]))
    counts = []
    for policy in policies:
        prow = [r for r in rows if r["policy"] == policy]
        groups = _group([r for r in prow if _involves(r["hazard"], who)], "ttc", "speed")
        cells = []
        for t in ttcs:
            for s in speeds:
                g = groups.get((t, s), [])
                counts.append(len(g))
                cells.append(_fmt(100.0 * _mean(g, column), 3) if g else MISSING)
        lines.append(_md_row([policy_label(policy)] + cells))
    overlap = [(t, s) for t in ttcs for s in speeds if (t, s) in next(iter(reference.values()))]
    if overlap:
        for policy, values in reference.items():
            cells = [values.get((t, s), MISSING) for t in ttcs for s in speeds]
            lines.append(_md_row([f"{policy_label(policy)} (paper, CARLA)"] + cells))
    lines.append("")
    lines.append(_count_note(counts, what))
    lines += notes
    if overlap:
        lines.append(
            "_Rows marked (paper, CARLA) are Porav & Newman's published values (CARLA simulator, their own test "
            f"bank), shown where the paper has that TTC × speed cell; {MISSING} = not reported._"
        )
    else:
        lines.append("_No TTC × speed cell of this grid is in the paper's table, so no reference row is shown._")
    return "\n".join(lines)


def table_i_markdown(rows: Sequence[dict]) -> str:
    return _ttc_speed_table(
        rows,
        "pedestrian_injury",
        "pedestrian",
        PAPER_TABLE_I,
        "Table I. Pedestrian probability (%) of severe injury",
        "hazard: pedestrian or both",
        [
            "_Value = 100 × mean over scenarios of the summed Rosen & Sander severe-injury probability of the "
            "pedestrians hit (0 when none is hit)._"
        ],
    )


def table_ii_markdown(rows: Sequence[dict]) -> str:
    return _ttc_speed_table(
        rows,
        "occupant_injury",
        "all",
        PAPER_TABLE_II,
        "Table II. Car occupant probability (%) of severe injury",
        "all hazards: pedestrian, car and both",
        [
            "_Value = 100 × mean over **all** scenarios of the summed Joksch severe-injury probability of every car "
            "occupant involved (ego and other car). Crashes into static objects (e.g. poles, walls) after a swerve "
            "count too._"
        ],
    )


def table_iii_markdown(rows: Sequence[dict]) -> str:
    ttcs = grid_of(rows)["ttcs"]
    lines = ["### Table III. Pedestrian collision rate (%) by TTC", ""]
    lines.append(_md_row(["TTC (s)"] + [_fmt_ttc(t) for t in ttcs]))
    lines.append(_md_row(["---"] + ["---:"] * len(ttcs)))
    counts = []
    for policy in policy_order(rows):
        groups = _group([r for r in rows if r["policy"] == policy and _involves(r["hazard"], "pedestrian")], "ttc")
        cells = []
        for t in ttcs:
            g = groups.get((t,), [])
            counts.append(len(g))
            cells.append(_fmt(100.0 * _mean(g, "pedestrian_collision"), 1) if g else MISSING)
        lines.append(_md_row([policy_label(policy)] + cells))
    for name, values in PAPER_TABLE_III.items():
        lines.append(_md_row([name] + [values.get(t, MISSING) for t in ttcs]))
    lines.append("")
    lines.append(_count_note(counts, "all speeds; hazard: pedestrian or both"))
    lines.append(
        "_Reference rows: Porav & Newman's R2 policy (CARLA) and Chae et al.'s DRL braking system as published; "
        f"NA = not available in the paper, {MISSING} = no published value at this TTC. Chae et al.'s row compares "
        "unlike things: their TTC is the time to the pedestrian's x when it starts to cross, and their collision "
        "is the car passing a 3 m safety line while the pedestrian crosses (a 'bump'), on a straight road with "
        "braking only; the like-for-like comparison is family `chae` (docs/results/chae/)._"
    )
    return "\n".join(lines)


def other_outcomes_markdown(rows: Sequence[dict]) -> str:
    """Secondary outcomes over every scenario of each policy (not in the paper, but needed to read Tables I–II)."""
    lines = ["### Other outcomes (all scenarios)", ""]
    head = [
        "Policy",
        "scenarios",
        "pedestrian coll. %",
        "vehicle coll. %",
        "static coll. %",
        "lane departure %",
        "mean speed at collision (m/s)",
    ]
    lines.append(_md_row(head))
    lines.append(_md_row(["---"] + ["---:"] * (len(head) - 1)))
    for policy in policy_order(rows):
        prow = [r for r in rows if r["policy"] == policy]
        lines.append(
            _md_row(
                [policy_label(policy), str(len(prow))]
                + [
                    _fmt(100.0 * _mean(prow, c), 1)
                    for c in ("pedestrian_collision", "vehicle_collision", "static_collision", "lane_departure")
                ]
                + [_fmt(_mean(prow, "speed_at_collision"), 2)]
            )
        )
    return "\n".join(lines)


def achievable_share_markdown(rows: Sequence[dict], baseline: str = "braking") -> str:
    """Table IV (ours): total severe-injury risk of braking and of the privileged planner per TTC × speed cell, and
    each policy's share of the improvement the planner shows is physically achievable. Empty without the planner."""
    shares = achievable_share_grids(rows, baseline)
    if not shares:
        return ""
    grid = grid_of(rows)
    ttcs, speeds = grid["ttcs"], grid["speeds"]
    lines = ["### Table IV. Share of the achievable improvement (%), total severe-injury risk", ""]
    header = ["Policy type", "whole bank"]
    for t in ttcs:
        header += [f"TTC {_fmt_ttc(t)} s"] + [""] * (len(speeds) - 1)
    lines.append(_md_row(header))
    lines.append(_md_row(["---"] + ["---:"] * (1 + len(ttcs) * len(speeds))))
    lines.append(_md_row(["*speed (m/s)*", ""] + [_fmt_speed(s) for _ in ttcs for s in speeds]))
    for policy in (baseline, CEILING):
        prow = [r for r in rows if r["policy"] == policy]
        arr = 100.0 * _metric_grid(prow, "total_injury", "all", ttcs, speeds)
        lines.append(
            _md_row(
                [f"{policy_label(policy)}: total injury risk (%)", _fmt(100.0 * _mean(prow, "total_injury"), 2)]
                + [_fmt(v, 2) for v in arr.ravel()]
            )
        )
    for policy, (_, _, arr) in shares.items():
        if policy == CEILING:
            continue
        lines.append(
            _md_row(
                [f"{policy_label(policy)}: share (%)", _fmt(overall_achievable_share(rows, policy, baseline), 0)]
                + [_fmt(v, 0) for v in arr.ravel()]
            )
        )
    lines += [
        "",
        "_Share = 100 × (braking − policy) / (braking − planner) of the mean total severe-injury risk "
        "(pedestrians + car occupants, the quantity R2 penalises) over all scenarios of a cell: 100 = as good as "
        "the privileged planner, 0 = no better than braking, negative = worse than braking; "
        f"{MISSING} = the planner improves on braking by less than {100 * MIN_ACHIEVABLE_GAIN:g} points there. "
        "The planner reads the true state and "
        "re-simulates brake/steer manoeuvres with the real dynamics (envs/planner.py)._",
    ]
    return "\n".join(lines)


def _apart(a: float, b: float) -> str:
    """``a / b`` with two decimals, or as many more (up to six) as it takes to show that they differ."""
    for digits in range(2, 7):
        left, right = f"{a:.{digits}f}", f"{b:.{digits}f}"
        if left != right:
            break
    return f"{left} / {right}"


def _cells_listed(cells: list[dict], near: bool) -> str:
    picked = [c for c in cells if (c["ttc"] <= 1.0) == near]
    return (
        "; ".join(
            f"{_fmt_speed(c['speed'])} m/s, {_fmt_ttc(c['ttc'])} s: {_apart(c['policy'], c['baseline'])}"
            + (f" (planner gain {c['planner_gain']:.2f})" if math.isfinite(c["planner_gain"]) else "")
            for c in picked
        )
        or "none"
    )


def cells_above_baseline_markdown(rows: Sequence[dict], baseline: str = "braking") -> str:
    """For every policy but the baseline and the planner: the cells where it is riskier than the baseline."""
    policies = [p for p in policy_order(rows) if p not in (baseline, CEILING)]
    if baseline not in policy_order(rows) or not policies:
        return ""
    lines = [f"### Cells where a policy's total risk is above {policy_label(baseline).lower()}'s", ""]
    lines.append(_md_row(["Policy", "TTC ≤ 1.0 s", "TTC > 1.0 s"]))
    lines.append(_md_row(["---", "---", "---"]))
    for policy in policies:
        cells = cells_above_baseline(rows, policy, baseline)
        lines.append(_md_row([policy_label(policy), _cells_listed(cells, True), _cells_listed(cells, False)]))
    lines += [
        "",
        f"_Mean total severe-injury risk (%) per cell, the policy's / {policy_label(baseline).lower()}'s, pooled "
        "over training seeds; the planner's gain is how many points below braking the privileged planner is "
        "there (under 0.5: braking is nearly as safe as anything can be)._",
    ]
    return "\n".join(lines)


def seed_spread_markdown(rows: Sequence[dict], baseline: str = "braking") -> str:
    """Mean ± standard deviation (min–max) over training seeds, for policies evaluated with two or more seeds."""
    spreads = {p: seed_spread(rows, p, baseline) for p in policy_order(rows)}
    spreads = {p: s for p, s in spreads.items() if s is not None}
    if not spreads:
        return ""
    names = {
        "pedestrian_collision_rate": "pedestrian coll. %",
        "static_collision_rate": "static coll. %",
        "pedestrian_severe_injury": "pedestrian injury %",
        "occupant_severe_injury": "occupant injury %",
        "total_severe_injury": "total injury %",
        "achievable_share": "share of achievable %",
    }
    lines = ["### Spread over training seeds", ""]
    lines.append(_md_row(["Policy", "seeds"] + list(names.values())))
    lines.append(_md_row(["---", "---"] + ["---:"] * len(names)))
    for policy, sp in spreads.items():
        cells = []
        for metric in names:
            st = sp["spread"][metric]
            k = 1.0 if metric == "achievable_share" else 100.0
            if st["mean"] is None:
                cells.append(MISSING)
            else:
                sd = "" if st["std"] is None else f" ± {k * st['std']:.1f}"
                cells.append(f"{k * st['mean']:.1f}{sd} ({k * st['min']:.1f}–{k * st['max']:.1f})")
        lines.append(_md_row([policy_label(policy), ", ".join(map(str, sp["seeds"]))] + cells))
    lines += [
        "",
        "_Mean ± standard deviation (min–max) over the seeds' whole-bank values. Every other table pools "
        "all seeds' rows, which equals the mean over seeds since each seed runs the same scenarios._",
    ]
    return "\n".join(lines)


def tables_markdown(rows: Sequence[dict]) -> str:
    """Tables I, II and III laid out as in the paper, plus a table of secondary outcomes, as Markdown."""
    rows = list(rows)
    if not rows:
        return "# Evaluation report\n\n_No evaluation rows._\n"
    grid = grid_of(rows)
    intro = (
        "# Evaluation report\n\n"
        f"Test bank: hazards {', '.join(grid['hazards'])}; TTC {', '.join(_fmt_ttc(t) for t in grid['ttcs'])} s; "
        f"speeds {', '.join(_fmt_speed(s) for s in grid['speeds'])} m/s; "
        f"policies {', '.join(policy_label(p) for p in policy_order(rows))}."
    )
    parts = [
        intro,
        table_i_markdown(rows),
        table_ii_markdown(rows),
        table_iii_markdown(rows),
        achievable_share_markdown(rows),
        cells_above_baseline_markdown(rows),
        other_outcomes_markdown(rows),
        seed_spread_markdown(rows),
    ]
    return "\n\n".join(p for p in parts if p) + "\n"
