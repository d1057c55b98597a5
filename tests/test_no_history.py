"""The product files speak of the project, never of how it was made: no numbered work sessions, no issue numbers,
no dates.

Scanned: the README, ``docs/``, ``conf/``, ``worldmodel/``, ``envs/``, ``experiments/``, ``benchmarks/``,
``tests/``, ``notebooks/`` (the cells' text, not their outputs) and ``data/README.md``, in the file kinds that carry
prose (Markdown, Python, YAML, notebooks, shell, TOML). ``CHANGELOG.md`` is where history belongs, and committed data
(JSON, CSV) may carry dates; so may the generated ``*_tables.md`` tables, in their numbers, and only dates are
allowed there. "Issues" in the sense of problems is fine: only "issue" followed by a number is history.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCANNED = (
    "README.md",
    "docs",
    "conf",
    "worldmodel",
    "envs",
    "experiments",
    "benchmarks",
    "tests",
    "notebooks",
    "data/README.md",
)
KINDS = (".md", ".py", ".yaml", ".yml", ".ipynb", ".sh", ".toml")
NEVER = ("CHANGELOG.md",)  # history's own file
DATED_DATA = "_tables.md"  # generated tables: dates allowed in their data, nothing else


_UNITS = ("first", "second", "third", "fourth", "fifth", "sixth", "seventh", "eighth", "ninth")
_ORDINAL_WORDS = (
    *_UNITS,
    "tenth",
    "eleventh",
    "twelfth",
    "thirteenth",
    "fourteenth",
    "fifteenth",
    "sixteenth",
    "seventeenth",
    "eighteenth",
    "nineteenth",
    "twentieth",
    *(f"twenty[- ]{u}" for u in _UNITS),
    "thirtieth",
)
_ORDINAL = r"(?:" + "|".join(_ORDINAL_WORDS) + r"|\d+(?:st|nd|rd|th))"
SESSION = re.compile(
    rf"\b{_ORDINAL}(?:\s+\w+)?\s+sessions?\b"  # an ordinal, perhaps one more word ("first twenty"), "session(s)"
    r"|\b(?:earlier|previous|prior|past)\s+sessions?\b",
    re.IGNORECASE,
)
ISSUE = re.compile(r"\bissues?[\s#-]*\d", re.IGNORECASE)  # "issue", "issues", then a number, "#" allowed
DATE = re.compile(r"\b\d{4}-(?:0[1-9]|1[0-2])-(?:0[1-9]|[12]\d|3[01])\b")  # ISO dates, YYYY-MM-DD


def scanned_files(root: Path = ROOT) -> list[Path]:
    """Every file of the scanned paths and kinds under ``root``, hidden folders (``.venv``, caches) left out."""
    files = []
    for name in SCANNED:
        top = root / name
        candidates = [top] if top.is_file() else sorted(top.rglob("*")) if top.is_dir() else []
        for path in candidates:
            rel = path.relative_to(root)
            if (
                path.is_file()
                and path.suffix in KINDS
                and path.name not in NEVER
                and not any(part.startswith(".") or part == "__pycache__" for part in rel.parts)
            ):
                files.append(path)
    return files


def text_lines(path: Path) -> list[tuple[str, str]]:
    """(where, line) for each line of ``path``; a notebook's lines are its cells' sources, outputs left out."""
    if path.suffix != ".ipynb":
        return [(str(i), line) for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)]
    cells = json.loads(path.read_text(encoding="utf-8")).get("cells", [])
    out = []
    for c, cell in enumerate(cells):
        source = cell.get("source", "")
        source = "".join(source) if isinstance(source, list) else source
        out += [(f"cell {c} line {i}", line) for i, line in enumerate(source.splitlines(), 1)]
    return out


def history_in(path: Path, root: Path = ROOT) -> list[str]:
    """``file:line: kind: text`` for every line of ``path`` that tells development history."""
    checks = [("numbered session", SESSION), ("issue number", ISSUE)]
    if not path.name.endswith(DATED_DATA):
        checks.append(("date", DATE))
    rel = path.relative_to(root).as_posix()
    hits = []
    for where, line in text_lines(path):
        for kind, pattern in checks:
            if pattern.search(line):
                hits.append(f"{rel}:{where}: {kind}: {line.strip()[:100]}")
    return hits


def test_the_product_files_carry_no_development_history():
    hits = [h for path in scanned_files() for h in history_in(path)]
    assert not hits, "development history in product files (say the fact, not when or why it came):\n" + "\n".join(hits)


def test_the_check_sees_sessions_issues_and_dates(tmp_path):
    """The check itself can fail: each kind of history is found, named by file and line, in every scanned kind;
    what is not history (a pytest session, problems called issues, a scenario number, a citation's year, a date
    format, a generated table's dates, the changelog, committed data, a virtual environment) is not."""
    session = "sess" + "ion"  # spelt apart so that this file scans clean itself
    bad = {
        "docs/design.md": f"intro\nTwentieth {session}: X gave Y.\n",
        "docs/results/chae/notes/x.md": f"as in the first twenty {session}s\n",
        "worldmodel/a.py": f'"""Doc."""\n\n# the 21st {session}\'s note\nx = 1  # since the 21st {session}\n',
        "envs/b.py": '"""Issue ' + '11\'s chooser."""\n',
        "experiments/c.py": "# (iss" + "ues 13-15)\n",
        "benchmarks/RESULTS.md": "Measured 2026-11" + "-24 with the bench.\n",
        "tests/test_x.py": f"# as in earlier {session}s\n",
        "conf/base.yaml": "# issue #" + "6\n",
        "data/README.md": "log of 2026-11" + "-22 00:48 UTC\n",
        "README.md": f"The third {session} found it.\n",
        "docs/results/agent/x_tables.md": f"| seventh {session} | 1 |\n",
    }
    nb = {"cells": [{"cell_type": "markdown", "source": ["# Title\n", "After iss" + "ue 12's bar\n"]}]}
    fine = {
        "tests/conftest.py": '@pytest.fixture(scope="' + session + '")\n# once per test ' + session + "\n",
        "worldmodel/d.py": '"""No issues with the camera; Scenario 2; Chae et al. (2017); "%Y-%m-%d"."""\n',
        "docs/results/chae/quick_tables.md": "| seed | date |\n| 3 | 2026-11" + "-24 |\n",
        "CHANGELOG.md": "## 2026-11" + f"-24\nthe seventh {session}, issue " + "11\n",
        "docs/results/ledger.json": '{"date": "2026-11' + '-24", "note": "issue ' + '11"}\n',
        "docs/results/ledger.csv": "2026-11" + "-24,issue " + "11\n",
        ".venv/lib/x.py": "# issue " + "11\n",
        "tests/.venv/y.py": "# issue " + "11\n",
    }
    for rel, text in {**bad, **fine}.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    (tmp_path / "notebooks").mkdir()
    (tmp_path / "notebooks" / "n.ipynb").write_text(json.dumps(nb))

    hits = [h for path in scanned_files(tmp_path) for h in history_in(path, tmp_path)]
    where = {h.split(": ")[0] for h in hits}
    assert where == {
        "docs/design.md:2",
        "docs/results/chae/notes/x.md:1",
        "worldmodel/a.py:3",
        "worldmodel/a.py:4",
        "envs/b.py:1",
        "experiments/c.py:1",
        "benchmarks/RESULTS.md:1",
        "tests/test_x.py:1",
        "conf/base.yaml:1",
        "data/README.md:1",
        "README.md:1",
        "docs/results/agent/x_tables.md:1",
        "notebooks/n.ipynb:cell 0 line 2",
    }, hits
    assert {h.split(": ")[1] for h in hits} == {"numbered session", "issue number", "date"}


def test_the_docs_stay_short_enough_to_read():
    """The README leads a newcomer in at most 250 lines; each results report is at most 200, with longer
    investigations in its notes/."""
    assert len((ROOT / "README.md").read_text().splitlines()) <= 250
    long = {
        str(p.relative_to(ROOT)): n
        for p in (ROOT / "docs" / "results").glob("*/README.md")
        if (n := len(p.read_text().splitlines())) > 200
    }
    assert not long, f"reports over 200 lines (move investigations to notes/): {long}"
