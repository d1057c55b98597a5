"""Mutation testing of the core numeric modules: ``make mutation`` (tests/README.md). Not part of CI.

Runs mutmut (its settings, the modules it mutates and the tests it runs, are in ``pyproject.toml`` under
``[tool.mutmut]``) on the mutants of ``TARGETS``, then prints per module how many mutants the tests kill, how many
survive, and how many no selected test reaches, and lists the survivors. ``--report`` only prints, from the
results of an earlier run.
"""

from __future__ import annotations

import argparse
import fnmatch
import subprocess
import sys
from collections import Counter, defaultdict
from pathlib import Path

# the injury model, the rewards, where scenarios put the ego and the hazards, the replay memories, and the report's
# statistics with the intervals and tests under them (its tables and figures are left out: a mutant there changes
# how a number is printed)
TARGETS = (
    "envs.injury.*",
    "envs.rewards.*",
    "envs.scenario.*",
    "envs.actors.*",
    "worldmodel.models.replay.*",
    "worldmodel.report.rows.x__mean__*",
    "worldmodel.report.rows.x__values__*",
    "worldmodel.report.summary.x__metrics__*",
    "worldmodel.report.summary.x_share_of_gain__*",
    "worldmodel.report.summary.x_achievable_share_grids__*",
    "worldmodel.report.summary.x_overall_achievable_share__*",
    "worldmodel.report.summary.x_paired_bootstrap__*",
    "worldmodel.report.summary.x_seed_spread__*",
    "worldmodel.report.summary.x_cells_above_baseline__*",
    "worldmodel.report.summary.x_summarize__*",
    "worldmodel.stats.*",
)
MUTMUT = Path(sys.executable).with_name("mutmut")


def results() -> dict[str, str]:
    """mutant name -> status (killed, survived, no tests, timeout, ...), for the mutants of ``TARGETS``."""
    out = subprocess.run([str(MUTMUT), "results", "--all", "true"], capture_output=True, text=True, check=True).stdout
    status = {}
    for line in out.splitlines():
        name, _, state = line.strip().rpartition(": ")
        if name and any(fnmatch.fnmatchcase(name, t) for t in TARGETS):
            status[name] = state
    return status


def module_of(name: str) -> str:
    return name.split(".x")[0]


def summary(status: dict[str, str]) -> str:
    by_module: dict[str, Counter] = defaultdict(Counter)
    for name, state in status.items():
        by_module[module_of(name)][state] += 1
    lines = [
        "| module | mutants | killed | survived | no test reaches it | other | survival |",
        "|---|---|---|---|---|---|---|",
    ]
    total: Counter = Counter()
    for module, counts in sorted(by_module.items()):
        total.update(counts)
        lines.append(row(module, counts))
    lines.append(row("all", total))
    survivors = sorted(n for n, s in status.items() if s in ("survived", "no tests"))
    lines += ["", f"{len(survivors)} mutants not killed:", *(f"  {n}: {status[n]}" for n in survivors)]
    return "\n".join(lines)


def row(name: str, counts: Counter) -> str:
    n = sum(counts.values())
    alive = counts["survived"] + counts["no tests"]
    other = n - alive - counts["killed"]
    rate = f"{100 * alive / n:.1f} %" if n else "n/a"
    return f"| {name} | {n} | {counts['killed']} | {counts['survived']} | {counts['no tests']} | {other} | {rate} |"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--report", action="store_true", help="print the results of the last run, run nothing")
    args = parser.parse_args()
    if not MUTMUT.exists():
        print(f"mutmut is not installed: `{sys.executable} -m pip install -r requirements-mutation.lock`")
        return 2
    if not args.report:
        run = subprocess.run([str(MUTMUT), "run", *TARGETS], check=False)
        if run.returncode != 0:
            # mutmut stops before any mutant when the selected tests fail on the code as it is
            print(
                f"mutmut run failed (exit status {run.returncode}); no mutant was judged. Run the tests it selects "
                "(pyproject.toml, [tool.mutmut]) on the unmutated code first: `.venv/bin/pytest -p no:xdist "
                "tests/test_banks.py ...`; a test that imports a folder mutmut does not copy needs it in also_copy",
                file=sys.stderr,
            )
            return 1
    status = results()
    print(summary(status))
    unmatched = [t for t in TARGETS if not any(fnmatch.fnmatchcase(name, t) for name in status)]
    if unmatched:
        # a renamed function silently leaves its mutants out of the run
        names = ", ".join(unmatched)
        print(f"no mutant matches {names}: a function renamed or removed? update TARGETS", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
