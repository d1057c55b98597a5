"""The rules of the scenario banks, whose seeds each family declares (worldmodel/registry.py), and the ledger of
the test banks (docs/design.md §6).

**Validation banks** are for choosing settings, checkpoints and rules, as often as needed. ``evaluate.bank``
defaults to ``validation``, so everyday runs (``make run``) never touch a test bank. The test suite runs with
``WORLDMODEL_TEST_SUITE=1`` (``tests/conftest.py``): its test banks are drawn from test-only seeds, and drawing a
real sealed seed there is an error, so no test ever evaluates on a real test bank.

**Test banks** are for final numbers only: one per scenario family, each drawn from a seed that no choice was ever
made on. An evaluation on one (``evaluate.bank=test``) appends a row to the ledger, ``docs/results/ledger.csv``:
the date, the commit, the family and bank, every policy with its model hashes, and the headline figure. A report
says how many rows its bank has. A configuration is judged on the test bank once; a configuration changed after its
test result is another configuration, with a row of its own, and the first result stays in the report.
"""

from __future__ import annotations

import csv
import datetime
import functools
import io
import logging
import os
import subprocess
from pathlib import Path

from . import registry

log = logging.getLogger(__name__)

# Each family declares its banks (worldmodel/registry.py): its validation draws, the default first (every seed that
# judged a configuration before the sealed banks existed stays there: those results steered choices, so they can only
# validate), its sealed test seed (drawn at random once, never used to choose) and the seed the test suite's "test
# bank" is drawn from instead.
IN_TEST_SUITE = os.environ.get("WORLDMODEL_TEST_SUITE") == "1"


def validation_seeds(family: str) -> tuple[int, ...]:
    return registry.family(family).validation_seeds


def test_seed(family: str) -> int:
    """The seed ``family``'s test bank is drawn from: its sealed seed, or in the test suite its stand-in."""
    f = registry.family(family)
    return f.suite_test_seed if IN_TEST_SUITE else f.sealed_seed


def sealed_seeds() -> set[int]:
    """Every family's sealed test seed."""
    return {f.sealed_seed for f in registry.families()}


BANKS = ("validation", "test")
REPO = Path(__file__).resolve().parents[1]
LEDGER = REPO / "docs" / "results" / "ledger.csv"
# rows_sha: SHA-256 of the evaluation's results.csv as written (the published rows, decompressed, are those bytes):
# recheck holds the published rows to it. Empty in a row recorded before the column.
LEDGER_COLUMNS = (
    "date",
    "commit",
    "experiment",
    "scale",
    "family",
    "bank_seed",
    "scenarios",
    "policies",
    "headline",
    "rows_sha",
)


def draw_seed(bank: str, family: str, validation_seed: int) -> int:
    """The seed a family's bank is drawn from: its sealed test seed, or ``validation_seed``."""
    if bank not in BANKS:
        raise ValueError(f"bank {bank!r}: use one of {', '.join(BANKS)}")
    seed = test_seed(family) if bank == "test" else int(validation_seed)
    if IN_TEST_SUITE and seed in sealed_seeds():
        raise RuntimeError(f"the test suite drew the sealed test seed {seed}: tests use each family's suite_test_seed")
    return seed


def dir_suffix(bank: str, family: str, validation_seed: int) -> str:
    """How an evaluation's folder tells its bank: nothing for the family's default validation draw, ``_test`` for
    the test bank, ``_seed<N>`` for another validation draw."""
    if bank == "test":
        return "_test"
    return "" if int(validation_seed) == validation_seeds(family)[0] else f"_seed{int(validation_seed)}"


def sealed_seed_problem(seed: int) -> str | None:
    """Why ``seed`` cannot be a validation draw (it is a family's sealed test seed), or None."""
    if int(seed) in {*sealed_seeds(), *(test_seed(f) for f in registry.names())}:
        return f"{seed} is a sealed test seed; evaluate on the test bank with evaluate.bank=test"
    return None


def seed_problems(section, key: str, prefix: str = ""):
    """A config section's validation draw ``key`` may not be a sealed test seed; ``prefix`` names the section in the
    error (``chae.``)."""
    from .common import ConfigValueError

    why = sealed_seed_problem(getattr(section, key))
    if why:
        yield ConfigValueError(prefix + key, getattr(section, key), why)


def ledger_key(row: dict) -> str:
    """The key a ledger row names an evaluation row's policy by: a trained one (``agent_*``) with its seed."""
    policy = str(row["policy"])
    return f"{policy}/seed{row['policy_seed']}" if policy.startswith("agent_") else policy


def validation_draw(text: str) -> int:
    """An argparse ``type`` for a script's bank seed: a whole number that is not a sealed test seed, since the
    experiments' draws choose settings and a test bank may only judge them."""
    import argparse

    seed = int(text)
    why = sealed_seed_problem(seed)
    if why:
        raise argparse.ArgumentTypeError(why.split(";")[0] + ": choose a validation draw (worldmodel/banks.py)")
    return seed


@functools.cache
def commit() -> str:
    """The checked-out commit, ``+dirty`` when tracked files differ from it; ``unknown`` outside git. Read once per
    process, at its start (``config.hydra_main``): the code that ran is the code checked out when it started, even
    if a commit lands while a long pipeline runs."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short=12", "HEAD"], cwd=REPO, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO, capture_output=True, text=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


def read_ledger(path: str | Path = LEDGER) -> list[dict]:
    path = Path(path)
    if not path.exists():
        return []
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def uses(family: str, seed: int | None = None, path: str | Path = LEDGER) -> int:
    """How many evaluations the ledger records on ``family``'s test bank (``seed``: its sealed seed by default)."""
    seed = test_seed(family) if seed is None else int(seed)
    return sum(1 for r in read_ledger(path) if r["family"] == family and int(r["bank_seed"]) == seed)


def record(
    path: str | Path,
    *,
    experiment: str,
    scale: str | None,
    family: str,
    scenarios: int,
    policies: dict[str, dict[str, str]],
    headline: dict[str, str],
    rows_sha: str = "",
) -> dict:
    """Append one evaluation on ``family``'s test bank to the ledger at ``path`` (created with its header).

    ``policies``: each policy's key -> its model hashes (empty for scripted ones); ``headline``: each policy's key
    -> its headline figure, as text with its unit; ``rows_sha``: the digest of its rows file. Appending never
    changes an earlier row (a ledger from before a column gets the column, empty in its rows)."""
    row = {
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "commit": commit(),
        "experiment": experiment,
        "scale": scale or "",
        "family": family,
        "bank_seed": test_seed(family),
        "scenarios": int(scenarios),
        "policies": "; ".join(
            f"{key}" + (f" ({', '.join(f'{k}={v}' for k, v in hashes.items() if v)})" if any(hashes.values()) else "")
            for key, hashes in policies.items()
        ),
        "headline": "; ".join(f"{key}: {figure}" for key, figure in headline.items()),
        "rows_sha": rows_sha,
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    new = not path.exists() or path.stat().st_size == 0
    if not new and path.read_text().split("\n", 1)[0] != ",".join(LEDGER_COLUMNS):
        _add_columns(path)
    with path.open("a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=LEDGER_COLUMNS, lineterminator="\n")
        if new:
            writer.writeheader()
        writer.writerow(row)
    return row


def _add_columns(path: Path) -> None:
    """Rewrite a ledger written before a column of ``LEDGER_COLUMNS`` with it, empty in the earlier rows."""
    from .common import StageError, atomic_write_text

    old = read_ledger(path)
    unknown = set(old[0]) - set(LEDGER_COLUMNS) if old else set()
    if unknown:
        raise StageError(f"{path} has columns this code does not know ({', '.join(sorted(unknown))}): update the code")
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=LEDGER_COLUMNS, lineterminator="\n", restval="")
    writer.writeheader()
    writer.writerows(old)
    atomic_write_text(path, buffer.getvalue())


def judged(cfg, family: str) -> list[dict]:
    """The ledger rows of ``family``'s test bank for this experiment: what that bank has already judged of it."""
    return [
        r
        for r in read_ledger(ledger_path(cfg))
        if r["experiment"] == cfg.experiment and r["family"] == family and int(r["bank_seed"]) == test_seed(family)
    ]


def sealed_bank_problem(cfg, family: str) -> str | None:
    """Why this evaluation may not run: ``family``'s test bank already judged this experiment (the ledger has its
    row) and ``evaluate.retest`` does not say that a changed configuration is meant. None on a validation bank."""
    if cfg.evaluate.bank != "test" or cfg.evaluate.retest:
        return None
    earlier = judged(cfg, family)
    if not earlier:
        return None
    last = earlier[-1]
    return (
        f"the {family} test bank already judged experiment {cfg.experiment!r} ({len(earlier)} ledger row(s), the "
        f"last on {last['date']} at commit {last['commit']}; {ledger_path(cfg)}); a test bank judges a "
        "configuration once. Read its result in the evaluation's folder. To judge a changed configuration, give it "
        "its own experiment name, or pass evaluate.retest=true to add its row beside the first"
    )


def ledger_path(cfg) -> Path:
    """``paths.ledger``, or the repository's ``docs/results/ledger.csv`` when it is empty."""
    from omegaconf import OmegaConf

    chosen = str(OmegaConf.select(cfg, "paths.ledger", default="") or "")
    return Path(chosen) if chosen else LEDGER


def record_evaluation(
    cfg, family: str, rows: Path, scenarios: int, policies: dict, headline: dict[str, str]
) -> dict | None:
    """The ledger row of an evaluation on ``family``'s test bank (``evaluate.bank=test``) whose rows are the file
    ``rows``; None on a validation bank, which the ledger does not count."""
    from omegaconf import OmegaConf

    if cfg.evaluate.bank != "test":
        return None
    from .common import file_sha256

    path = ledger_path(cfg)
    row = record(
        path,
        experiment=cfg.experiment,
        scale=OmegaConf.select(cfg, "scale_name", default=None),
        family=family,
        scenarios=scenarios,
        policies=policies,
        headline=headline,
        rows_sha=file_sha256(rows) if rows.exists() else "",
    )
    log.info(
        "[eval] %s test bank (seed %d): ledger row %d for this bank, %s",
        family,
        test_seed(family),
        uses(family, path=path),
        path,
    )
    return row
