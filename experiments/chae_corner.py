"""Where Chae's agents fail, from an evaluation's ``results.csv`` (``evaluate evaluate.family=chae``).

    python -m experiments.chae_corner runs/NAME/eval_chae/results.csv [--policy ensemble] [--ttc 1.5]

For every policy whose name contains ``--policy``, and each of its seeds: the ego's initial speeds (km/h) of the
Scenario-1 trials that bumped at TTC ``--ttc``, and Scenario 2's needless stops per 10 km/h band of initial speed.
Shows whether the failures sit in a corner of the training range
(docs/results/chae/notes/training_ttcs_and_value_rescaling.md).
"""

from __future__ import annotations

import argparse
import csv
from collections import defaultdict
from pathlib import Path

BAND_KMH = 10


def corner(rows: list[dict], ttc: float) -> dict:
    """Per (policy, seed): the sorted km/h of the bumps at ``ttc``, and {band's lower km/h: needless stop %}."""
    bumps, stops = defaultdict(list), defaultdict(lambda: defaultdict(lambda: [0, 0]))
    for r in rows:
        key, kmh = (r["policy"], int(r["policy_seed"])), float(r["v_init"]) * 3.6
        if r["scenario"] == "1" and float(r["ttc"]) == ttc and r["bump"] == "1":
            bumps[key].append(round(kmh, 1))
        elif r["scenario"] == "2":
            band = stops[key][min(int(kmh // BAND_KMH) * BAND_KMH, 50)]  # 60 km/h itself joins 50-60
            band[0] += r["end"] == "stop"
            band[1] += 1
    return {
        key: (sorted(bumps[key]), {b: 100 * k / n for b, (k, n) in sorted(stops[key].items())})
        for key in sorted(set(bumps) | set(stops))
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path)
    parser.add_argument("--policy", default="ensemble", help="a part of the policies' names")
    parser.add_argument("--ttc", type=float, default=1.5)
    args = parser.parse_args(argv)
    if not args.results.is_file():
        raise SystemExit(
            f"{args.results} does not exist: run `python -m worldmodel.evaluate evaluate.family=chae` first"
        )
    with args.results.open() as f:
        rows = [r for r in csv.DictReader(f) if args.policy in r["policy"]]
    for (policy, seed), (bumps, stops) in corner(rows, args.ttc).items():
        bands = ", ".join(f"{b}-{b + BAND_KMH} km/h {p:.1f} %" for b, p in stops.items())
        at = f"at {bumps} km/h" if bumps else "none"
        print(f"{policy} seed {seed}: bumps at TTC {args.ttc:g} s {at}; needless stops {bands}")


if __name__ == "__main__":
    main()
