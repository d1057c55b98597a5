"""Time two commands against each other as whole processes, in alternating pairs (A B A B ...), and print each one's
median wall and CPU seconds and the median of the per-pair ratios A/B. Pairing keeps the ratio meaningful when the
machine's speed drifts (another job on the cores) during the measurement.

    python -m benchmarks.ab -n 5 --a "python -m benchmarks.digest_cost check" \
        --b "python -m benchmarks.digest_cost load"

Each command runs without a shell (split as a shell splits words), its output thrown away. Peak memory is the
largest child's (``ru_maxrss``), for the commands run so far.
"""

from __future__ import annotations

import argparse
import resource
import shlex
import statistics
import subprocess
import time


def timed(command: list[str]) -> tuple[float, float]:
    """(wall seconds, user + system seconds) of one run of ``command`` and the children it waited for."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--a", required=True, help="the command measured")
    parser.add_argument("--b", required=True, help="the baseline it is measured against")
    parser.add_argument("-n", type=int, default=5, help="pairs counted, after one pair not counted")
    args = parser.parse_args(argv)
    a, b = shlex.split(args.a), shlex.split(args.b)
    timed(a), timed(b)  # warm the file cache and the imports
    runs = {"A": [], "B": []}
    for _ in range(args.n):
        runs["A"].append(timed(a))
        runs["B"].append(timed(b))
    for name in ("A", "B"):
        walls, cpus = zip(*runs[name])
        print(
            f"{name}: wall {statistics.median(walls):.3f} s (min {min(walls):.3f}, max {max(walls):.3f}), "
            f"cpu {statistics.median(cpus):.3f} s"
        )
    ratios = [ra[0] / rb[0] for ra, rb in zip(runs["A"], runs["B"])]
    print(
        f"A/B wall: {statistics.median(ratios):.3f} (pairs {min(ratios):.3f}-{max(ratios):.3f}); "
        f"peak child memory {resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024:.0f} MiB"
    )


if __name__ == "__main__":
    main()
