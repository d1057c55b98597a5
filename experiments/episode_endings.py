"""How the paper family's episodes end, per policy: crash, stop, leaving the scene or the time limit.

    python -m experiments.episode_endings docs/results/porav/validation.rows.csv.gz [runs/NAME/eval/results.csv ...]

For each rows file (a committed ``*.rows.csv.gz`` or an evaluation's ``results.csv``; ``--pool`` joins them into
one table) a markdown table with one line per policy, its training seeds pooled: the share of episodes that ended
in a crash with a vehicle, a crash with a static object, stopped (final speed below ``--stopped`` m/s at the time
limit, without a crash), left the scene (``UrbanCollisionEnv``'s ``left_scene``), or reached the time limit still
moving; the share with a pedestrian hit (which does not end an episode, so it overlaps the others); and the mean R2
cost (minus ``return_r2``) of all episodes and of those that left the scene.

Rows written since evaluation records how each episode ended (``end``, ``final_speed``) are classified from those.
Older rows (the committed ones) lack them, and the ending is inferred: a vehicle collision is a crash with a vehicle
(also when a static object was hit in the same step), else a static collision a crash with a static object; else an
episode shorter than its horizon (``envs.env.horizon_steps`` of its TTC, the env's default ``horizon_after_ttc_s``
and ``step_s`` unless given) left the scene; else it reached the time limit, stopped or moving, which those rows
cannot tell apart ("time limit (stopped or moving)"). An episode that left the scene on its very last step reads as
the time limit there. The rows do not record where the hazard was when the ego left, so that is not reported.
Reads rows only: nothing is simulated; ~1 s for the paper-scale validation bank.
"""

from __future__ import annotations

import argparse
import math
from collections import Counter
from pathlib import Path

from envs.env import DT, HORIZON_AFTER_TTC_S, horizon_steps
from worldmodel.report import policy_order, read_results_csv

VEHICLE, STATIC, STOPPED, LEFT, MOVING, TIME_LIMIT = (
    "crash: vehicle",
    "crash: static object",
    "stopped",
    "left the scene",
    "time limit, moving",
    "time limit (stopped or moving)",
)
ENDINGS = (VEHICLE, STATIC, STOPPED, LEFT, MOVING, TIME_LIMIT)


def ending(row: dict, stopped: float, step_s: float, horizon_after_ttc_s: float) -> str:
    """How ``row``'s episode ended, one of ``ENDINGS`` (or a family's own end, as the env named it)."""
    end = row.get("end")
    if end:  # recorded by the env
        if end == "crash":
            if row["vehicle_collision"]:
                return VEHICLE
            if row["static_collision"]:
                return STATIC
            raise ValueError(f"a crash without a vehicle or static collision: {row}")
        if end == "left_scene":
            return LEFT
        if end == "horizon":
            return STOPPED if row["final_speed"] < stopped else MOVING
        return str(end)
    if row["vehicle_collision"]:
        return VEHICLE
    if row["static_collision"]:
        return STATIC
    horizon = horizon_steps(float(row["ttc"]), step_s, horizon_after_ttc_s)
    if row["steps"] > horizon:
        raise ValueError(
            f"{row['policy']} scenario {row['scenario_id']} ran {row['steps']} steps, past its horizon of {horizon}: "
            "these rows were made with another --step-s or --horizon-after-ttc-s"
        )
    return LEFT if row["steps"] < horizon else TIME_LIMIT


def _mean(values: list[float]) -> float:
    return sum(values) / len(values) if values else math.nan


def _pct(n: int, total: int) -> str:
    return f"{100 * n / total:.1f}" if total else "—"


def table(rows: list[dict], stopped: float, step_s: float, horizon_after_ttc_s: float) -> str:
    """One markdown line per policy: the share of each ending (%), pedestrian hits, mean R2 costs."""
    by_policy: dict[str, list[tuple[str, dict]]] = {}
    for r in rows:
        by_policy.setdefault(r["policy"], []).append((ending(r, stopped, step_s, horizon_after_ttc_s), r))
    seen = Counter(e for pairs in by_policy.values() for e, _ in pairs)
    # crashes and exits always; stopped and moving where some rows record their end, the undivided time limit where
    # some do not; a family's own ends after them
    recorded, inferred = any(r.get("end") for r in rows), not all(r.get("end") for r in rows)
    shown = {VEHICLE, STATIC, LEFT} | ({STOPPED, MOVING} if recorded else set()) | ({TIME_LIMIT} if inferred else set())
    columns = [e for e in ENDINGS if e in shown] + sorted(set(seen) - set(ENDINGS))
    head = ["policy", "episodes", *(f"{c} %" for c in columns), "pedestrian hit %", "R2 cost, all", "R2 cost, left"]
    lines = ["| " + " | ".join(head) + " |", "|---|" + "---:|" * (len(head) - 1)]
    for policy in policy_order(rows):
        pairs = by_policy[policy]
        counts = Counter(e for e, _ in pairs)
        n = len(pairs)
        cost_all = _mean([-r["return_r2"] for _, r in pairs])
        cost_left = _mean([-r["return_r2"] for e, r in pairs if e == LEFT])
        cells = [policy, str(n), *(_pct(counts[c], n) for c in columns)]
        cells += [_pct(sum(bool(r["pedestrian_collision"]) for _, r in pairs), n)]
        cells += [f"{cost_all:.4f}", "—" if math.isnan(cost_left) else f"{cost_left:.4f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rows", nargs="+", type=Path, help="rows files: *.rows.csv.gz or runs/NAME/eval*/results.csv")
    parser.add_argument("--pool", action="store_true", help="one table of all the files' rows together")
    parser.add_argument("--stopped", type=float, default=0.5, help="m/s: below this at the time limit is stopped")
    parser.add_argument("--step-s", type=float, default=DT, help="the env's step the rows were made with")
    parser.add_argument(
        "--horizon-after-ttc-s", type=float, default=HORIZON_AFTER_TTC_S, help="the env's horizon_after_ttc_s"
    )
    args = parser.parse_args(argv)
    groups = {" + ".join(map(str, args.rows)): []} if args.pool else {str(p): [] for p in args.rows}
    for path in args.rows:
        groups[next(iter(groups)) if args.pool else str(path)] += read_results_csv(path)
    for name, rows in groups.items():
        recorded = sum(bool(r.get("end")) for r in rows)
        how = "recorded" if recorded == len(rows) else "inferred" if not recorded else "recorded or inferred"
        print(f"### {name}: {len(rows)} episodes, endings {how}\n")
        print(table(rows, args.stopped, args.step_s, args.horizon_after_ttc_s))
        print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
