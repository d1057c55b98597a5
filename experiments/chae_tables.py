"""One set of Chae tables from several evaluations of the same draw (``evaluate evaluate.family=chae``).

    python -m experiments.chae_tables runs/A/eval_chae/results.csv runs/B/eval_chae/results.csv --out tables.md

A large draw can be split over processes, each driving some of the policies (``evaluate.chae.policies``, and the
ensembles of the seeds each experiment holds); this joins their ``results.csv`` rows and writes the tables the
evaluation writes (``chae.system.tables``), with the bars judged run by run. The evaluations must share the draw
(``evaluate.chae.seed``, ``trials``, ``ttcs``): a (policy, seed) that appears in two files, or files with
different trials, is refused.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

INTS = ("policy_seed", "scenario", "far_side", "bump", "contact")
FLOATS = ("ttc", "v_init", "v_ped", "impact_speed", "pedestrian_injury", "stop_gap")


def read(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        r.update({k: int(r[k]) for k in INTS})
        r.update({k: float(r[k]) for k in FLOATS})
    return rows


def trial_keys(rows: list[dict]) -> dict:
    """Per (policy, seed): the trials it drove, as (scenario, ttc, v_init, v_ped) in order."""
    out: dict = {}
    for r in rows:
        out.setdefault((r["policy"], r["policy_seed"]), []).append((r["scenario"], r["ttc"], r["v_init"], r["v_ped"]))
    return out


def join(paths: list[Path]) -> list[dict]:
    rows, trials, source = [], None, {}
    for path in paths:
        mine = read(path)
        for key, drawn in trial_keys(mine).items():
            if key in source:
                raise SystemExit(f"{key[0]} seed {key[1]} is in both {source[key]} and {path}: give each run once")
            if trials is not None and drawn != trials:
                raise SystemExit(
                    f"{path} drove other trials than {paths[0]}: evaluate the same draw (seed, trials, ttcs)"
                )
            source[key], trials = path, drawn
        rows += mine
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path, nargs="+", help="evaluations' results.csv, of the same draw")
    parser.add_argument("--out", type=Path, required=True, help="the tables, markdown")
    args = parser.parse_args(argv)

    from worldmodel.families.chae import system as chae

    rows = join(args.results)
    ttcs = sorted({r["ttc"] for r in rows if r["scenario"] == 1})
    first_run = trial_keys(rows)[rows[0]["policy"], rows[0]["policy_seed"]]
    trials = sum(scenario == 2 for scenario, *_ in first_run)  # Scenario 2 has as many trials as each TTC
    args.out.write_text(chae.tables(chae.summarise(rows, ttcs), trials))
    print(f"{len(rows)} rows from {len(args.results)} files: {args.out}")


if __name__ == "__main__":
    main()
