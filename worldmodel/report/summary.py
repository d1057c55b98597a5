"""What the rows add up to: per-cell metrics, improvement over braking, the share of the achievable improvement,
paired-bootstrap intervals, the spread over training seeds, and the cells where a policy is riskier than braking."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from worldmodel import stats

from .rows import _involves, _json_number, _key, _mean, grid_of, policy_label, policy_order

CEILING = "oracle"
# Below this gap in mean total injury between the baseline and the ceiling (0.5 percentage points), a cell has
# too little to gain for a ratio to mean anything: at paper scale a 0.01-point gap turned a 0.2-point loss into
# a "share" of -200,000 %. Such cells show n/a.
MIN_ACHIEVABLE_GAIN = 0.005


# Per-cell metrics of summarize(): name -> (row key, how to average).  "nanmean" ignores NaN (no collision).
CELL_METRICS = {
    "pedestrian_collision_rate": "pedestrian_collision",
    "vehicle_collision_rate": "vehicle_collision",
    "static_collision_rate": "static_collision",
    "lane_departure_rate": "lane_departure",
    "pedestrian_severe_injury": "pedestrian_injury",
    "occupant_severe_injury": "occupant_injury",
    "ego_occupant_severe_injury": "ego_occupant_injury",
    "mean_pedestrians_hit": "n_pedestrians_hit",
    "mean_speed_at_collision": "speed_at_collision",
    "mean_steps": "steps",
    "mean_return_r1": "return_r1",
    "mean_return_r2": "return_r2",
    "total_severe_injury": "total_injury",
}
# Metrics whose mean and spread over training seeds are reported for policies evaluated with several seeds.
SEED_METRICS = (
    "pedestrian_collision_rate",
    "vehicle_collision_rate",
    "static_collision_rate",
    "lane_departure_rate",
    "pedestrian_severe_injury",
    "occupant_severe_injury",
    "total_severe_injury",
)

# Fig. 5 columns: key -> (title, row key, which scenarios count).
IMPROVEMENT_METRICS = {
    "pedestrian_collision": ("(a) pedestrian collision rate", "pedestrian_collision", "pedestrian"),
    "pedestrian_injury": ("(b) pedestrian severe-injury risk", "pedestrian_injury", "pedestrian"),
    "car_collision": ("(c) car collision rate", "vehicle_collision", "car"),
    "occupant_injury": ("(d) occupant severe-injury risk", "occupant_injury", "all"),
}


# ----------------------------------------------------------------------------- summary
def _metrics(rows: Sequence[dict]) -> dict[str, Any]:
    out: dict[str, Any] = {name: _json_number(_mean(rows, col)) for name, col in CELL_METRICS.items()}
    any_hit = [
        float(
            bool(r.get("pedestrian_collision")) or bool(r.get("vehicle_collision")) or bool(r.get("static_collision"))
        )
        for r in rows
    ]
    out["any_collision_rate"] = _json_number(float(np.mean(any_hit))) if any_hit else None
    out["count"] = len(rows)
    return out


def _group(rows: Sequence[dict], *fields: str) -> dict[tuple, list[dict]]:
    groups: dict[tuple, list[dict]] = {}
    rounded: dict = {}  # each distinct TTC and speed rounded once: a bank's rows repeat a handful of them
    for r in rows:
        key = tuple(
            (rounded[r[f]] if r[f] in rounded else rounded.setdefault(r[f], _key(r[f])))
            if f in ("ttc", "speed")
            else str(r[f])
            for f in fields
        )
        groups.setdefault(key, []).append(r)
    return groups


def _grid_to_json(ttcs, speeds, arr) -> dict:
    return {
        "ttcs": list(ttcs),
        "speeds": list(speeds),
        "values": [[_json_number(float(v)) for v in line] for line in np.asarray(arr)],
    }


def _policy_entry(policy: str, prow: list[dict], hazard_rank: dict[str, int]) -> dict:
    """One policy's part of the summary: overall, by hazard, Table III's rates by TTC, and every cell."""
    cells = []
    for (hazard, ttc, speed), group in sorted(
        _group(prow, "hazard", "ttc", "speed").items(), key=lambda kv: (hazard_rank[kv[0][0]], kv[0][1], kv[0][2])
    ):
        cells.append({"hazard": hazard, "ttc": ttc, "speed": speed, **_metrics(group)})
    by_hazard = [
        {"hazard": h, **_metrics(g)}
        for (h,), g in sorted(_group(prow, "hazard").items(), key=lambda kv: hazard_rank[kv[0][0]])
    ]
    ped = [r for r in prow if _involves(r["hazard"], "pedestrian")]
    by_ttc = [
        {"ttc": t, "rate": _json_number(_mean(g, "pedestrian_collision")), "count": len(g)}
        for (t,), g in sorted(_group(ped, "ttc").items())
    ]
    return {
        "label": policy_label(policy),
        "overall": _metrics(prow),
        "by_hazard": by_hazard,
        "pedestrian_collision_rate_by_ttc": by_ttc,
        "cells": cells,
    }


def summarize(rows: Sequence[dict], baseline: str = "braking") -> dict:
    """Aggregate rows per policy and per cell (hazard, TTC, speed). JSON-serialisable, no NaN (None instead).

    Structure::

        {"schema": 1,
         "grid": {"hazards": [...], "ttcs": [...], "speeds": [...], "policies": [...], "n_rows": int,
                  "scenarios_per_cell": {"min": int, "max": int}},
         "baseline": "braking",
         "policies": {name: {"label": str,
                             "overall": {metric: value, ..., "count": int},          # every scenario
                             "by_hazard": [{"hazard": str, metric: value, ..., "count": int}],
                             "pedestrian_collision_rate_by_ttc": [{"ttc", "rate", "count"}],  # Table III
                             "cells": [{"hazard", "ttc", "speed", metric: value, ..., "count"}]}},
         "improvement": {policy: {metric: {"ttcs", "speeds", "values" (percentage points, None = no data)}}},
         "achievable_share": {"ceiling": "oracle", "definition": str,          # only with oracle rows
                              "policies": {policy: {"overall": %, "cells": {"ttcs", "speeds", "values" (%)}}}}}

    Each policy also has "seeds" (training seeds present; 0 for scripted policies) and, with two or more seeds,
    "seed_spread" (see ``seed_spread``); its other numbers pool every seed's rows.
    Metrics are fractions (rates in 0..1, injuries as mean probabilities); only "improvement" is in points.
    """
    rows = list(rows)
    grid = grid_of(rows)
    policies = policy_order(rows)
    counts = [len(g) for g in _group(rows, "policy", "hazard", "ttc", "speed").values()]
    out: dict[str, Any] = {
        "schema": 1,
        "grid": {
            **grid,
            "policies": policies,
            "n_rows": len(rows),
            "scenarios_per_cell": {"min": min(counts) if counts else 0, "max": max(counts) if counts else 0},
        },
        "baseline": baseline,
        "policies": {},
        "improvement": {},
    }
    hazard_rank = {h: i for i, h in enumerate(grid["hazards"])}
    for policy in policies:
        out["policies"][policy] = _policy_entry(policy, [r for r in rows if r["policy"] == policy], hazard_rank)
    if baseline in policies:
        for policy, metrics in improvement_grids(rows, baseline).items():
            out["improvement"][policy] = {m: _grid_to_json(*g) for m, g in metrics.items()}
    shares = achievable_share_grids(rows, baseline)
    if shares:
        out["achievable_share"] = {
            "ceiling": CEILING,
            "definition": "100 * (baseline - policy) / (baseline - ceiling) of the mean total severe-injury risk",
            "policies": {
                p: {"overall": _json_number(overall_achievable_share(rows, p, baseline)), "cells": _grid_to_json(*g)}
                for p, g in shares.items()
            },
        }
    for policy in policies:
        out["policies"][policy]["seeds"] = policy_seeds(rows, policy)
        spread = seed_spread(rows, policy, baseline)
        if spread is not None:
            out["policies"][policy]["seed_spread"] = spread
    return out


# ----------------------------------------------------------------------------- grids (Fig. 5)
def _metric_grid(rows: Sequence[dict], column: str, who: str, ttcs, speeds) -> np.ndarray:
    """Mean of ``column`` per (TTC, speed) over scenarios involving ``who``; NaN where there are none."""
    arr = np.full((len(ttcs), len(speeds)), np.nan)
    groups = _group([r for r in rows if _involves(r["hazard"], who)], "ttc", "speed")
    for i, t in enumerate(ttcs):
        for j, s in enumerate(speeds):
            if (t, s) in groups:
                arr[i, j] = _mean(groups[(t, s)], column)
    return arr


def absolute_grids(rows: Sequence[dict], policy: str) -> dict[str, tuple[list, list, np.ndarray]]:
    """metric -> (ttcs, speeds, array[len(ttcs), len(speeds)]) of ``policy``'s own values in % (×100)."""
    grid = grid_of(rows)
    prow = [r for r in rows if r["policy"] == policy]
    return {
        m: (grid["ttcs"], grid["speeds"], 100.0 * _metric_grid(prow, col, who, grid["ttcs"], grid["speeds"]))
        for m, (_, col, who) in IMPROVEMENT_METRICS.items()
    }


def improvement_grids(rows: Sequence[dict], baseline: str = "braking") -> dict[str, dict[str, tuple]]:
    """policy -> metric -> (ttcs, speeds, array[len(ttcs), len(speeds)]) of baseline − policy in percentage points.

    Positive = the policy is better (fewer collisions / lower injury risk) than ``baseline``. Metrics:
    ``pedestrian_collision`` and ``pedestrian_injury`` over pedestrian/both hazards, ``car_collision`` over
    car/both hazards, ``occupant_injury`` over all hazards. NaN where either side has no scenario in that cell.
    Every policy other than the baseline appears; ``ValueError`` if the baseline has no rows.
    """
    rows = list(rows)
    policies = policy_order(rows)
    if baseline not in policies:
        raise ValueError(f"baseline policy {baseline!r} has no rows (policies present: {policies})")
    base = absolute_grids(rows, baseline)
    out = {}
    for policy in policies:
        if policy == baseline:
            continue
        mine = absolute_grids(rows, policy)
        out[policy] = {m: (base[m][0], base[m][1], base[m][2] - mine[m][2]) for m in IMPROVEMENT_METRICS}
    return out


def share_of_gain(base, policy, ceiling):
    """100 (base - policy) / (base - ceiling), NaN where the gap is under ``MIN_ACHIEVABLE_GAIN``: of numbers, a
    float; of arrays (a bootstrap's resamples), an array."""
    gain = np.asarray(base, dtype=float) - ceiling
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(np.isfinite(gain) & (gain >= MIN_ACHIEVABLE_GAIN), 100.0 * (base - policy) / gain, np.nan)
    return float(out) if out.ndim == 0 else out


def achievable_share_grids(
    rows: Sequence[dict], baseline: str = "braking", ceiling: str = CEILING
) -> dict[str, tuple[list, list, np.ndarray]]:
    """policy -> (ttcs, speeds, array) of the share of the achievable improvement in %, per TTC × speed cell:
    100 × (baseline − policy) / (baseline − ceiling) of the mean total severe-injury risk over all scenarios of
    the cell. 100 = as good as the privileged planner, 0 = no better than braking, negative = worse than braking.
    NaN where the planner barely improves on braking (gap below ``MIN_ACHIEVABLE_GAIN``). Empty without a ceiling."""
    rows = list(rows)
    policies = policy_order(rows)
    if baseline not in policies or ceiling not in policies:
        return {}
    grid = grid_of(rows)
    ttcs, speeds = grid["ttcs"], grid["speeds"]

    def totals(policy):
        return _metric_grid([r for r in rows if r["policy"] == policy], "total_injury", "all", ttcs, speeds)

    base, top = totals(baseline), totals(ceiling)
    out = {}
    for policy in policies:
        if policy == baseline:
            continue
        mine = totals(policy)
        arr = share_of_gain(base, mine, top) if base.size else base
        out[policy] = (ttcs, speeds, np.asarray(arr, dtype=float))
    return out


def overall_achievable_share(
    rows: Sequence[dict], policy: str, baseline: str = "braking", ceiling: str = CEILING
) -> float:
    """The share of the achievable improvement over the whole bank, in % (NaN without a ceiling or a gap)."""

    def total(p):
        return _mean([r for r in rows if r["policy"] == p], "total_injury")

    return share_of_gain(total(baseline), total(policy), total(ceiling))


def paired_bootstrap(
    rows: Sequence[dict],
    policy: str,
    baseline: str = "braking",
    ceiling: str = CEILING,
    n: int = 2000,
    seed: int = 0,
) -> dict:
    """Paired bootstrap over scenarios of the whole-bank share of the achievable improvement and of the difference
    in mean total risk against ``baseline`` (policy − baseline, in points; negative = fewer injuries). Every
    policy's risk is first averaged over its training seeds per scenario; each resample draws scenarios with
    replacement and uses the same draw for all three policies (``stats.paired_bootstrap_ci``). Returns the point
    estimates and 95 % percentile intervals; the share's is n/a where the share is, and where some resample has
    too little to gain for one."""

    def per_scenario(name: str) -> dict:
        risk: dict = {}
        for r in rows:
            if r["policy"] == name:
                risk.setdefault(r["scenario_id"], []).append(r["pedestrian_injury"] + r["occupant_injury"])
        return {k: float(np.mean(v)) for k, v in risk.items()}

    p, b, o = per_scenario(policy), per_scenario(baseline), per_scenario(ceiling)
    ids = sorted(set(p) & set(b) & set(o))
    if not ids:
        raise ValueError(f"no scenario has rows of {policy}, {baseline} and {ceiling}")
    risks = [np.array([d[i] for i in ids]) for d in (p, b, o)]

    def share(mine, base, top, axis=-1):  # a resample with too little to gain has no share, as a bank has none
        return share_of_gain(base.mean(axis), mine.mean(axis), top.mean(axis))

    def difference(mine, base, axis=-1):
        return 100.0 * (mine.mean(axis) - base.mean(axis))

    point = share_of_gain(risks[1].mean(), risks[0].mean(), risks[2].mean())
    share_ci = stats.paired_bootstrap_ci(risks, share, n, seed) if math.isfinite(point) else (math.nan, math.nan)
    return {
        "scenarios": len(ids),
        "share": point,
        "share_ci95": list(share_ci),
        "difference_pts": float(difference(risks[0], risks[1])),
        "difference_ci95": list(stats.paired_bootstrap_ci(risks[:2], difference, n, seed)),
    }


def policy_seeds(rows: Sequence[dict], policy: str) -> list[int]:
    return sorted({int(r.get("policy_seed") or 0) for r in rows if r["policy"] == policy})


def seed_spread(rows: Sequence[dict], policy: str, baseline: str = "braking") -> dict | None:
    """Mean, standard deviation (n − 1), min and max over training seeds of ``SEED_METRICS`` and of the share of
    the achievable improvement, with each seed's own values; None for a policy evaluated with one seed."""
    seeds = policy_seeds(rows, policy)
    if len(seeds) < 2:
        return None
    others = [r for r in rows if r["policy"] != policy]
    per_seed = {}
    for seed in seeds:
        mine = [r for r in rows if r["policy"] == policy and int(r.get("policy_seed") or 0) == seed]
        metrics = {m: _mean(mine, CELL_METRICS[m]) for m in SEED_METRICS}
        metrics["achievable_share"] = overall_achievable_share(others + mine, policy, baseline)
        per_seed[seed] = metrics
    spread = {}
    for metric in (*SEED_METRICS, "achievable_share"):
        vals = np.array([per_seed[s][metric] for s in seeds], dtype=float)
        vals = vals[np.isfinite(vals)]
        spread[metric] = {
            "mean": _json_number(float(vals.mean())) if vals.size else None,
            "std": _json_number(float(vals.std(ddof=1))) if vals.size > 1 else None,
            "min": _json_number(float(vals.min())) if vals.size else None,
            "max": _json_number(float(vals.max())) if vals.size else None,
        }
    return {
        "seeds": seeds,
        "spread": spread,
        "by_seed": {str(s): {m: _json_number(v) for m, v in per_seed[s].items()} for s in seeds},
    }


def cells_above_baseline(rows: Sequence[dict], policy: str, baseline: str = "braking") -> list[dict]:
    """The TTC × speed cells where ``policy``'s mean total severe-injury risk (pooled over its seeds) is above
    ``baseline``'s, each with both risks and the planner's gain over the baseline there (NaN without the planner),
    in points. A learned policy should never be worse than braking where braking is nearly safe."""
    grid = grid_of(rows)
    ttcs, speeds = grid["ttcs"], grid["speeds"]

    def totals(name):
        return 100.0 * _metric_grid([r for r in rows if r["policy"] == name], "total_injury", "all", ttcs, speeds)

    mine, base = totals(policy), totals(baseline)
    top = totals(CEILING) if CEILING in policy_order(rows) else np.full_like(base, np.nan)
    out = []
    for i, ttc in enumerate(ttcs):
        for j, speed in enumerate(speeds):
            if mine[i, j] > base[i, j] + 1e-9:
                cell = {"ttc": ttc, "speed": speed, "policy": float(mine[i, j]), "baseline": float(base[i, j])}
                out.append({**cell, "planner_gain": float(base[i, j] - top[i, j])})
    return out
