"""python -m worldmodel.report publish | headline | pooled | recheck | readme: the committed results' command
(worldmodel/report/published.py, worldmodel/report/recheck.py)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from worldmodel import report
from worldmodel.common import atomic_write_text
from worldmodel.report.published import (
    POOLED,
    README,
    RESULTS,
    RecheckError,
    pooled,
    publish,
    readme_table,
    readme_with_table,
    write_headline,
)
from worldmodel.report.recheck import published_tables, recheck, rowless_tables


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m worldmodel.report",
        description="Commit the per-scenario rows behind the tables in docs/results/, and rebuild or re-check the "
        "tables from them.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("publish", help="commit an evaluation's rows and render its tables from them")
    p.add_argument("eval_dir", type=Path)
    p.add_argument("stem", type=Path, help="e.g. docs/results/porav/test: writes test.rows.csv.gz, test.tables.md, ...")
    p.add_argument("--command", dest="made_by", required=True, help="the command that made the evaluation")
    p = sub.add_parser("headline", help="the validation-and-test table of a directory")
    p.add_argument("directory", type=Path)
    p = sub.add_parser("pooled", help="a directory's validation banks pooled, written to its pooled.md")
    p.add_argument("directory", type=Path)
    p = sub.add_parser("recheck", help="recompute every committed table from its rows")
    p.add_argument("directory", type=Path, nargs="?", default=RESULTS)
    p = sub.add_parser("readme", help="regenerate the README's result table")
    p.add_argument("--check", action="store_true", help="only say whether it is up to date")
    args = parser.parse_args(argv)
    try:
        if args.command == "publish":
            publish(args.eval_dir, args.stem, args.made_by)
        elif args.command == "headline":
            write_headline(args.directory)
        elif args.command == "pooled":
            atomic_write_text(Path(args.directory) / POOLED, pooled(args.directory))
        elif args.command == "recheck":
            problems = recheck(args.directory)
            for problem in problems:
                print(problem)
            if problems:
                return 1
            rowless = rowless_tables(args.directory)
            for path in rowless:
                print(f"not rechecked, no rows beside it: {path}")
            checked = len(published_tables(args.directory))
            print(
                f"every table with rows under {args.directory} ({checked}) is what its rows give, and "
                f"every test-bank evaluation is the one its ledger recorded; {len(rowless)} tables without rows "
                "were not rechecked (listed above)"
            )
        elif args.command == "readme":
            text = README.read_text()
            fresh = readme_with_table(text, readme_table())
            if args.check:
                if fresh != text:
                    print("README.md's result table differs from docs/results: run python -m worldmodel.report readme")
                    return 1
            else:
                atomic_write_text(README, fresh)
    except (RecheckError, report.MalformedRowsError) as err:
        print(f"error: {err}")
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
