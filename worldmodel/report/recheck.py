"""Recheck: every committed table under ``docs/results/`` rendered again from the rows beside it, and every published
test-bank evaluation held to the ledger row that recorded it (``python -m worldmodel.report recheck``; what is
committed and how: worldmodel/report/published.py)."""

from __future__ import annotations

import gzip
import hashlib
import json
from collections import Counter
from pathlib import Path

from .. import banks, registry
from .published import (
    ACTION_EFFECT,
    NCAP,
    POOLED,
    ROWS,
    TABLES,
    first_difference,
    headline,
    pooled,
    published,
    render_tables,
)


def ledger_of(directory: Path) -> Path | None:
    """The ``ledger.csv`` that records ``directory``'s test-bank evaluations: its own, or the nearest above it."""
    for folder in (Path(directory).resolve(), *Path(directory).resolve().parents):
        if (folder / "ledger.csv").exists():
            return folder / "ledger.csv"
    return None


def _ledger_policies(text: str) -> dict[str, dict[str, str]]:
    """A ledger row's ``policies`` cell: each policy's key -> its model hashes (``actor=...``, ``members=a+b``)."""
    out = {}
    for part in filter(None, (p.strip() for p in text.split("; "))):
        key, _, hashes = part.partition(" (")
        out[key] = dict(h.split("=", 1) for h in hashes.rstrip(")").split(", ") if "=" in h)
    return out


def _ledger_mismatch(rows: list[dict], entry: dict) -> str | None:
    """How ``rows`` differ from what the ledger row ``entry`` recorded of its evaluation; None when they agree."""
    recorded = _ledger_policies(entry["policies"])
    counts = Counter(banks.ledger_key(r) for r in rows)
    if set(counts) != set(recorded):
        extra, missing = sorted(set(counts) - set(recorded)), sorted(set(recorded) - set(counts))
        return f"policies differ (in the rows only: {extra or 'none'}; in the ledger only: {missing or 'none'})"
    wrong = sorted(k for k, n in counts.items() if n != int(entry["scenarios"]))
    if wrong:
        return f"{wrong[0]} has {counts[wrong[0]]} rows, the ledger {entry['scenarios']} scenarios"
    # the experiment's world model, by the hashes the ledger names for the agents that see through it
    world_model = {name: {m[name] for m in recorded.values() if m.get(name)} for name in ("vae", "rnn")}
    for r in rows:
        key = banks.ledger_key(r)
        for name in ("vae", "rnn", "actor"):
            value = r.get(f"{name}_sha")
            if not value or recorded[key].get(name) == value:
                continue
            if name != "actor" and name not in recorded[key] and value in world_model[name]:
                # rows written before they followed a preset's own input named the experiment's world model for an
                # agent that reads none (agent=counterfactual_true_state): the ledger says it reads none
                continue
            return f"{key}'s {name} is {value} in the rows, {recorded[key].get(name)} in the ledger"
    return None


def rows_sha(rows_path: Path) -> str:
    """SHA-256 of a published rows file's content: the evaluation's ``results.csv`` as it was written."""
    return hashlib.sha256(gzip.decompress(Path(rows_path).read_bytes())).hexdigest()


def ledger_problems(stem: str, rows: list[dict], meta: dict, ledger: Path | None, digest: str = "") -> list[str]:
    """Why the published test-bank evaluation ``stem`` (its rows, and ``digest``: their file's ``rows_sha``) is not
    the one a ledger row recorded (empty: it is). A ledger row recorded before digests holds none to compare."""
    if meta.get("bank") != "test":
        return []
    where = f"{meta['family']} test bank (seed {meta['bank_seed']}), experiment {meta['experiment']!r}"
    if ledger is None:
        return [f"{stem}: no ledger.csv in its folder or above it records the {where}"]
    entries = [
        e
        for e in banks.read_ledger(ledger)
        if e["family"] == meta["family"]
        and int(e["bank_seed"]) == int(meta["bank_seed"])
        and e["experiment"] == meta["experiment"]
    ]
    if not entries:
        return [f"{stem}: {ledger} has no row for the {where}; publish only an evaluation the ledger recorded"]
    mismatches = [
        f"their SHA-256 is {digest[:12]}, the ledger recorded {e['rows_sha'][:12]}"
        if e.get("rows_sha") and digest and e["rows_sha"] != digest
        else _ledger_mismatch(rows, e)
        for e in entries
    ]
    if all(mismatches):
        # with several rows for the bank, the nearest: one that lists the same policies, if any does
        nearest = next((m for m in mismatches if not m.startswith("policies differ")), mismatches[-1])
        return [f"{stem}: the rows are not the evaluation {ledger} recorded for the {where}: {nearest}"]
    return []


def row_count_problems(stem: str, rows: list[dict], meta: dict) -> list[str]:
    """Why ``rows`` cannot be a whole evaluation: every policy and seed drives the same scenarios, so each has as
    many rows as the others (a multiple of the trials the meta file declares, where it declares them). A row removed
    or added may leave every rounded table figure as it was; this does not."""
    counts = Counter((str(r.get("policy")), str(r.get("policy_seed", ""))) for r in rows)
    if not counts:
        return [f"{stem}: no rows"]
    usual, _ = Counter(counts.values()).most_common(1)[0]
    odd = {key: n for key, n in counts.items() if n != usual}
    trials = meta.get("render", {}).get("trials")
    problems = [
        f"{stem}: {policy} (seed {seed or '-'}) has {n} rows where every other policy and seed has {usual}: a row "
        "was removed or added since it was published; restore the file from git"
        for (policy, seed), n in sorted(odd.items())
    ]
    if trials and usual % int(trials):
        problems.append(
            f"{stem}: {usual} rows per policy and seed, not a multiple of the {trials} trials its meta declares"
        )
    return problems


def recheck_directory(directory: Path, ledger: Path | None = None) -> list[str]:
    """What differs in one directory (empty: every table is what its rows give, and every test-bank evaluation is
    the one its ledger recorded). ``ledger``: the ledger to hold them to, by default ``ledger_of(directory)``."""
    directory = Path(directory)
    problems = []
    evaluations = published(directory)
    ledger = ledger or ledger_of(directory)
    for stem, (rows, meta) in evaluations.items():
        digest = rows_sha(directory / (stem + ROWS)) if meta.get("bank") == "test" else ""
        problems += ledger_problems(stem, rows, meta, ledger, digest)
        if meta["family"] not in (NCAP, ACTION_EFFECT):
            problems += row_count_problems(stem, rows, meta)
        path = directory / (stem + TABLES)
        if not path.exists():
            problems.append(f"{path} is missing: publish the evaluation again")
            continue
        diff = first_difference(str(path), path.read_text(), render_tables(rows, meta))
        if diff:
            problems.append(diff)
    if (directory / POOLED).exists():
        diff = first_difference(str(directory / POOLED), (directory / POOLED).read_text(), pooled(directory))
        if diff:
            problems.append(diff)
    paper = registry.default().name
    paper_only = all(meta["family"] == paper for _, meta in evaluations.values())
    if (directory / "headline.md").exists() or (paper_only and {"validation", "test"} <= set(evaluations)):
        text, data = headline(directory)
        for name, fresh in (("headline.md", text), ("headline.json", json.dumps(data, indent=2) + "\n")):
            path = directory / name
            committed = path.read_text() if path.exists() else ""
            diff = first_difference(str(path), committed, fresh)
            if diff:
                problems.append(diff)
    return problems


def recheck(root: Path, ledger: Path | None = None) -> list[str]:
    """``recheck_directory`` on ``root`` and every directory below it that holds published rows."""
    root = Path(root)
    directories = sorted({p.parent for p in root.rglob("*" + ROWS)} | ({root} if root.is_dir() else set()))
    return [problem for d in directories for problem in recheck_directory(d, ledger)]


def published_tables(root: Path) -> list[Path]:
    """The tables under ``root`` that ``publish`` rendered from the committed rows beside them."""
    root = Path(root)
    found = root.rglob("*" + TABLES) if root.is_dir() else ()
    return sorted(p for p in found if p.with_name(p.name.removesuffix(TABLES) + ROWS).exists())


def rowless_tables(root: Path) -> list[Path]:
    """The tables under ``root`` with no committed rows beside them (investigations' figures, kept as rendered):
    ``recheck`` cannot hold them to anything, and says so."""
    root = Path(root)
    found = root.rglob("*tables.md") if root.is_dir() else ()
    return sorted(set(found) - set(published_tables(root)))
