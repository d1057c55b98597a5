"""Reports of the evaluation test bank: CSV, JSON summary, the paper's Tables I–III and a Fig. 5-style heatmap.

Input is one *row* (a dict) per test scenario and policy, as produced by the evaluation stage::

    policy, scenario_id, hazard, ttc, speed, seed,
    pedestrian_collision, vehicle_collision, static_collision, lane_departure,   # 0/1
    n_pedestrians_hit, pedestrian_injury, occupant_injury, ego_occupant_injury,
    speed_at_collision (NaN if no collision), steps, return_r1, return_r2

Any subset of the grid hazard × TTC × speed and any set of policies is accepted; the grid is read off the rows.

Choices made here (the paper is silent on them):

* A cell is (hazard, TTC, speed). A metric of a cell is the plain mean over that cell's scenarios.
* "Hazard involves a pedestrian" means hazard ``pedestrian`` or ``both``; "involves a car" means ``car`` or ``both``.
  Pedestrian metrics (Table I, Table III, Fig. 5 a/b) average over pedestrian-involving scenarios only, so a
  car-only scenario, where no pedestrian is in danger, does not dilute them. Car-collision rate (Fig. 5 c) averages
  over car-involving scenarios. Occupant injury (Table II, Fig. 5 d) averages over *all* scenarios: swerving
  away from a pedestrian into a pole hurts the occupants too and must count against the policy.
* Improvement is ``baseline − policy`` in percentage points (×100), so positive means better than straight-line
  braking, as in the paper's Fig. 5 ("the more red, the lower the rate compared to braking").  Because every
  policy runs the *same* seeded scenarios, the difference of means equals the mean paired difference.
* Figures are built on ``matplotlib.figure.Figure`` with an explicit Agg canvas and never through ``pyplot``, so
  importing or calling this module never switches the backend of a notebook or opens a window.
* Every file is written atomically (temporary file + ``os.replace``), so a crash never leaves half a report.
"""

from __future__ import annotations

import csv
import gzip
import io
import json
import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from worldmodel import stats
from worldmodel.common import atomic_write_bytes, atomic_write_text

# ----------------------------------------------------------------------------- row schema
INT_COLUMNS = (
    "policy_seed",
    "scenario_id",
    "seed",
    "pedestrian_collision",
    "vehicle_collision",
    "static_collision",
    "lane_departure",
    "n_pedestrians_hit",
    "steps",
)
FLOAT_COLUMNS = (
    "ttc",
    "speed",
    "pedestrian_injury",
    "occupant_injury",
    "ego_occupant_injury",
    "speed_at_collision",
    "return_r1",
    "return_r2",
)
# Short SHA-256 of the VAE, LSTM and actor checkpoints that produced an agent's row (empty for scripted policies).
MODEL_COLUMNS = ("vae_sha", "rnn_sha", "actor_sha")
STR_COLUMNS = ("policy", "hazard", *MODEL_COLUMNS)
# A row: which policy and scenario, the scenario's outcome (envs' info["outcome"]), the models behind the policy.
ROW_META = ("policy", "policy_seed", "scenario_id", "hazard", "ttc", "speed", "seed")
OUTCOME_COLUMNS = (
    "pedestrian_collision",
    "vehicle_collision",
    "static_collision",
    "lane_departure",
    "n_pedestrians_hit",
    "pedestrian_injury",
    "occupant_injury",
    "ego_occupant_injury",
    "speed_at_collision",
    "steps",
    "return_r1",
    "return_r2",
)
COLUMNS = (*ROW_META, *OUTCOME_COLUMNS, *MODEL_COLUMNS)

POLICY_ORDER = ("braking", "agent_r1", "agent_r2", "oracle")
POLICY_LABELS = {
    "braking": "Straight-line braking",
    "agent_r1": "Brake&Steer, reward 1",
    "agent_r2": "Brake&Steer, reward 2",
    "agent_r2_chooser": "Chooser (brake, then one lane change), reward 2",
    "agent_r2_dag": "Cloned from the planner with 2 DAgger rounds, reward 2",
    "agent_r2_chooser_tele": "Chooser, frame band from a 30° second camera, reward 2",
    "oracle": "Privileged planner (oracle)",
    "oracle_brake1": "Planner after 1 frame of straight braking (perception ceiling)",
    "oracle_brake2": "Planner after 2 frames of straight braking (perception ceiling)",
}
CEILING = "oracle"
# Below this gap in mean total injury between the baseline and the ceiling (0.5 percentage points), a cell has
# too little to gain for a ratio to mean anything: at paper scale a 0.01-point gap turned a 0.2-point loss into
# a "share" of -200,000 %. Such cells show n/a.
MIN_ACHIEVABLE_GAIN = 0.005
HAZARD_ORDER = ("pedestrian", "car", "both")

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


# ----------------------------------------------------------------------------- small helpers
def _key(x: Any) -> float:
    """Grid coordinate used for grouping (robust to float noise from CSV or arithmetic)."""
    return round(float(x), 6)


def _involves(hazard: str, who: str) -> bool:
    h = str(hazard).lower()
    if who == "all":
        return True
    if who == "pedestrian":
        return h == "both" or "pedestrian" in h
    if who == "car":
        return h == "both" or "car" in h or "vehicle" in h
    raise ValueError(f"unknown participant {who!r}")


def _ordered(values: Iterable[str], order: Sequence[str]) -> list[str]:
    values = set(values)
    head = [v for v in order if v in values]
    return head + sorted(values - set(head))


def policy_order(rows: Sequence[dict]) -> list[str]:
    """Policies in report order: braking, agent_r1, agent_r2, then the rest alphabetically."""
    return _ordered((r["policy"] for r in rows), POLICY_ORDER)


def policy_label(policy: str) -> str:
    return POLICY_LABELS.get(policy, policy)


def grid_of(rows: Sequence[dict]) -> dict[str, list]:
    """The hazards, TTCs and speeds present in ``rows`` (sorted; hazards in pedestrian, car, both order)."""
    return {
        "hazards": _ordered((str(r["hazard"]) for r in rows), HAZARD_ORDER),
        "ttcs": sorted({_key(r["ttc"]) for r in rows}),
        "speeds": sorted({_key(r["speed"]) for r in rows}),
    }


def _values(rows: Sequence[dict], column: str) -> np.ndarray:
    vals = []
    for r in rows:
        # total_injury: everyone's severe-injury probabilities summed, which R2 penalises and the planner minimises
        v = r["pedestrian_injury"] + r["occupant_injury"] if column == "total_injury" else r.get(column)
        vals.append(np.nan if v is None else float(v))
    return np.asarray(vals, dtype=float)


def _mean(rows: Sequence[dict], column: str) -> float:
    """Mean of ``column`` ignoring NaN/None; NaN when there is nothing to average."""
    vals = _values(rows, column)
    vals = vals[np.isfinite(vals)]
    return float(vals.mean()) if vals.size else math.nan


def _json_number(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def _fmt_ttc(t: float) -> str:
    return f"{t:.1f}" if float(t).is_integer() else f"{t:g}"


def _fmt_speed(s: float) -> str:
    return f"{s:g}"


# ----------------------------------------------------------------------------- CSV
def _csv_cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, (bool, np.bool_)):
        return str(int(v))
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))  # shortest exact round-trip form; NaN -> "nan"
    return str(v)


def _parse_cell(column: str, text: str) -> Any:
    if column in STR_COLUMNS:
        return text
    if column in FLOAT_COLUMNS:
        return math.nan if text == "" else float(text)
    if column in INT_COLUMNS:
        if text == "":
            return None
        try:
            return int(text)
        except ValueError:
            return int(float(text))
    # A column this module does not know: infer int, then float, else keep the string.
    if text == "":
        return None
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def write_results_csv(rows: Sequence[dict], path: str | Path) -> Path:
    """Write one line per row, known columns first, extra keys after them in sorted order. Atomic. A path ending
    in ``.gz`` is gzip-compressed, with no timestamp, so the same rows always give the same bytes."""
    extra = sorted({k for r in rows for k in r} - set(COLUMNS))
    fields = list(COLUMNS) + extra
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(fields)
    for r in rows:
        writer.writerow([_csv_cell(r.get(k)) for k in fields])
    path = Path(path)
    if path.suffix == ".gz":
        atomic_write_bytes(path, gzip.compress(buf.getvalue().encode(), compresslevel=9, mtime=0))
    else:
        atomic_write_text(path, buf.getvalue())
    return path


def read_results_csv(path: str | Path) -> list[dict]:
    """Read a CSV written by ``write_results_csv`` (``.gz`` too) with its types restored (ints, floats incl. NaN,
    strs)."""
    path = Path(path)
    with gzip.open(path, "rt", newline="") if path.suffix == ".gz" else open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        return [{k: _parse_cell(k, v) for k, v in line.items()} for line in reader]


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
    for r in rows:
        key = tuple(_key(r[f]) if f in ("ttc", "speed") else str(r[f]) for f in fields)
        groups.setdefault(key, []).append(r)
    return groups


def _grid_to_json(ttcs, speeds, arr) -> dict:
    return {
        "ttcs": list(ttcs),
        "speeds": list(speeds),
        "values": [[_json_number(float(v)) for v in line] for line in np.asarray(arr)],
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
        prow = [r for r in rows if r["policy"] == policy]
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
        out["policies"][policy] = {
            "label": policy_label(policy),
            "overall": _metrics(prow),
            "by_hazard": by_hazard,
            "pedestrian_collision_rate_by_ttc": by_ttc,
            "cells": cells,
        }
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


def _share(base, policy, ceiling):
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
        arr = _share(base, mine, top) if base.size else base
        out[policy] = (ttcs, speeds, np.asarray(arr, dtype=float))
    return out


def overall_achievable_share(
    rows: Sequence[dict], policy: str, baseline: str = "braking", ceiling: str = CEILING
) -> float:
    """The share of the achievable improvement over the whole bank, in % (NaN without a ceiling or a gap)."""

    def total(p):
        return _mean([r for r in rows if r["policy"] == p], "total_injury")

    return _share(total(baseline), total(policy), total(ceiling))


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
        return _share(base.mean(axis), mine.mean(axis), top.mean(axis))

    def difference(mine, base, axis=-1):
        return 100.0 * (mine.mean(axis) - base.mean(axis))

    point = _share(risks[1].mean(), risks[0].mean(), risks[2].mean())
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


def _draw_heatmap(fig, ax, ttcs, speeds, arr, vmin, vmax, cmap, title):
    data = np.ma.masked_invalid(np.asarray(arr, dtype=float))
    cmap = _cmap(cmap)
    im = ax.imshow(data, cmap=cmap, vmin=vmin, vmax=vmax, origin="lower", aspect="auto")
    ax.set_xticks(range(len(speeds)), [_fmt_speed(s) for s in speeds])
    ax.set_yticks(range(len(ttcs)), [_fmt_ttc(t) for t in ttcs])
    ax.set_xlabel("initial speed (m/s)")
    ax.set_ylabel("TTC (s)")
    ax.set_title(title, fontsize=9)
    span = max(abs(vmin), abs(vmax)) or 1.0
    digits = 1 if span >= 5 else 2 if span >= 0.5 else 3  # paper-scale injury risks are fractions of a point
    small = len(ttcs) * len(speeds) > 40
    for i in range(len(ttcs)):
        for j in range(len(speeds)):
            v = float(np.asarray(arr)[i, j])
            if math.isfinite(v):
                v = 0.0 if round(v, digits) == 0 else v  # no "-0.0" from float noise
                text, colour = f"{v:.{digits}f}", ("white" if abs(v) > 0.6 * span else "black")
            else:
                text, colour = "n/a", "0.35"
            ax.text(j, i, text, ha="center", va="center", fontsize=6 if small else 8, color=colour)
    fig.colorbar(im, ax=ax, fraction=0.08, pad=0.03)


def _cmap(name: str):
    import matplotlib

    return matplotlib.colormaps[name].with_extremes(bad="0.85")


def heatmaps_figure(rows: Sequence[dict], baseline: str = "braking"):
    """Fig. 5 of the paper: one row per non-baseline policy, columns (a)–(d), improvement over the baseline.

    Each panel is TTC (y) × initial speed (x), diverging colormap centred at 0 (red = better than the
    baseline), with a symmetric colour range shared down each column. With nothing to compare (only the
    baseline, or no baseline at all) it draws every present policy's absolute values in % instead and says so
    in the title. Returns a ``matplotlib.figure.Figure`` (Agg canvas, pyplot untouched).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = list(rows)
    policies = policy_order(rows)
    metrics = list(IMPROVEMENT_METRICS)
    shares: dict = {}
    if baseline in policies and len(policies) > 1:
        grids = improvement_grids(rows, baseline)
        panel_rows = [(p, grids[p]) for p in policies if p != baseline]
        mode = "improvement"
        shares = achievable_share_grids(rows, baseline)
    else:
        panel_rows = [(p, absolute_grids(rows, p)) for p in policies]
        mode = "absolute"
    n_cols = len(metrics) + (1 if shares else 0)

    n_rows = max(1, len(panel_rows))
    grid = grid_of(rows)
    row_h = 1.1 + 0.35 * max(3, len(grid["ttcs"]))  # titles and tick labels + the TTC cells
    fig = Figure(figsize=(4.2 * n_cols, row_h * n_rows + 0.5), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(n_rows, n_cols, squeeze=False)

    if not panel_rows:  # no rows at all
        for ax, m in zip(axes[0], metrics):
            ax.set_title(IMPROVEMENT_METRICS[m][0], fontsize=9)
            ax.text(0.5, 0.5, "no data", ha="center", va="center", transform=ax.transAxes)
            ax.set_axis_off()
        fig.suptitle("No evaluation rows to report")
        return fig

    for col, m in enumerate(metrics):
        finite = [np.abs(g[m][2][np.isfinite(g[m][2])]) for _, g in panel_rows]
        peak = max((float(f.max()) for f in finite if f.size), default=0.0)
        peak = peak if peak > 0 else 1.0
        for row, (policy, g) in enumerate(panel_rows):
            ttcs, speeds, arr = g[m]
            title = f"{policy_label(policy)}\n{IMPROVEMENT_METRICS[m][0]}"
            if mode == "improvement":
                _draw_heatmap(fig, axes[row, col], ttcs, speeds, arr, -peak, peak, "RdBu_r", title + " (pp)")
            else:
                _draw_heatmap(fig, axes[row, col], ttcs, speeds, arr, 0.0, peak, "Reds", title + " (%)")
    for row, (policy, _) in enumerate(panel_rows if shares else []):
        # Fixed range: 100 % = as good as the planner; values past +-100 keep their number, saturate in colour.
        _draw_heatmap(
            fig,
            axes[row, -1],
            *shares[policy],
            -100.0,
            100.0,
            "RdBu_r",
            f"{policy_label(policy)}\n(e) share of achievable improvement,\ntotal injury risk (%)",
        )
    if mode == "improvement":
        fig.suptitle(
            f"Percentage-point improvement over {policy_label(baseline).lower()} "
            "(baseline − policy; red/positive = better)"
        )
    else:
        who = ", ".join(policy_label(p) for p, _ in panel_rows)
        why = "only the baseline was evaluated" if baseline in policies else f"baseline {baseline!r} missing"
        fig.suptitle(f"No policy to compare ({why}): absolute values (%) for {who}")
    return fig


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


# ----------------------------------------------------------------------------- everything at once
def _render_rgb(fig) -> np.ndarray:
    """Draw ``fig`` once on its Agg canvas and return the pixels as an (H, W, 3) uint8 array."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = fig.canvas if isinstance(fig.canvas, FigureCanvasAgg) else FigureCanvasAgg(fig)
    canvas.draw()
    return np.array(canvas.buffer_rgba())[..., :3]


def _png_bytes(rgb: np.ndarray, dpi: float) -> bytes:
    from matplotlib.image import imsave

    buf = io.BytesIO()
    imsave(buf, rgb, format="png", dpi=dpi)
    return buf.getvalue()


def write_report(
    rows: Sequence[dict], out_dir: str | Path, tb_writer=None, step: int = 0, baseline: str = "braking"
) -> dict:
    """Write ``summary.json``, ``tables.md`` and ``heatmaps.png`` into ``out_dir`` (atomically); return the summary.

    With a ``torch.utils.tensorboard.SummaryWriter`` it also logs the heatmap figure as an image
    (``report/heatmaps``, the same pixels ``add_figure`` would log, from a single draw), the
    tables as text (``report/tables``) and each policy's overall rates as scalars (``report/<policy>/<metric>``).
    """
    rows = list(rows)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = summarize(rows, baseline=baseline)
    tables = tables_markdown(rows)
    fig = heatmaps_figure(rows, baseline=baseline)
    atomic_write_text(out_dir / "summary.json", json.dumps(summary, indent=2, allow_nan=False) + "\n")
    atomic_write_text(out_dir / "tables.md", tables)
    rgb = _render_rgb(fig)  # drawn once (constrained layout is the slow part), reused for the PNG and TensorBoard
    atomic_write_bytes(out_dir / "heatmaps.png", _png_bytes(rgb, fig.dpi))
    if tb_writer is not None:
        # Exactly what SummaryWriter.add_figure logs (canvas pixels, RGB, as an image), minus a second draw.
        tb_writer.add_image("report/heatmaps", rgb, global_step=step, dataformats="HWC")
        tb_writer.add_text("report/tables", tables, global_step=step)
        for policy, entry in summary["policies"].items():
            for metric in (
                "pedestrian_collision_rate",
                "vehicle_collision_rate",
                "static_collision_rate",
                "pedestrian_severe_injury",
                "occupant_severe_injury",
            ):
                value = entry["overall"][metric]
                if value is not None:
                    tb_writer.add_scalar(f"report/{policy}/{metric}", value, global_step=step)
        tb_writer.flush()
    return summary


if __name__ == "__main__":  # python -m worldmodel.report publish | headline | recheck | readme
    from worldmodel.published import main

    raise SystemExit(main())
