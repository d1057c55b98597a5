"""Committed results: the rows behind every table, and the command that recomputes the tables from them."""

from __future__ import annotations

import gzip
import json
import re

import pytest

from worldmodel import banks, evaluate
from worldmodel.report import __main__ as report_cli
from worldmodel.report import published, read_results_csv, recheck, write_results_csv

TEST_SEED = banks.test_seed("porav")  # the suite's test-only stand-in for the sealed seed
TINY = ["evaluate.ttcs=[0.75,1.5]", "evaluate.speeds=[20.0]", "evaluate.hazards=[pedestrian]", "evaluate.per_cell=3"]
POLICIES = "evaluate.policies=[braking,oracle,oracle_brake1]"


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """The real evaluation on a tiny grid, on its validation and its test bank, published into docs/results/x."""
    from worldmodel.config import compose

    root = tmp_path_factory.mktemp("published")

    def cfg(*overrides):
        paths = [f"paths.runs_root={root}/runs", f"paths.data_root={root}/data", f"paths.ledger={root}/ledger.csv"]
        return compose("evaluate", [*paths, "experiment=t", "scale=smoke", *TINY, POLICIES, *overrides])

    evaluate.run(cfg())
    evaluate.run(cfg("evaluate.validation_seed=4712"))
    evaluate.run(cfg("evaluate.bank=test"))
    stages = {"collect": 90.0, "agent_r1": 300.0, "agent_r1/seed1": 360.0, "eval": 30.0, "eval_test": 30.0}
    timings = {name: {"wall_s": wall, "peak_rss_mb": 1.0, "scale": "smoke"} for name, wall in stages.items()}
    (root / "runs/t/pipeline.json").write_text(json.dumps(timings))  # as a pipeline run would have left it
    out = root / "docs" / "results" / "x"
    published.publish(root / "runs/t/eval", out / "validation", "make tiny")
    published.publish(root / "runs/t/eval_test", out / "test", "make tiny")
    published.write_headline(out)
    # a second validation bank, and the two pooled
    published.publish(root / "runs/t/eval_seed4712", out / "validation4712", "make tiny")
    (out / published.POOLED).write_text(published.pooled(out))
    return root, out


def test_published_rows_are_the_evaluation_rows_and_give_its_tables(results):
    root, out = results
    rows = gzip.decompress((out / "test.rows.csv.gz").read_bytes())
    assert rows == (root / "runs/t/eval_test/results.csv").read_bytes()
    assert (out / "test.tables.md").read_text() == (root / "runs/t/eval_test/tables.md").read_text()
    meta = json.loads((out / "test.meta.json").read_text())
    assert meta["bank"] == "test" and meta["bank_seed"] == TEST_SEED and meta["command"] == "make tiny"
    assert json.loads((out / "validation.meta.json").read_text())["bank_seed"] == 4711
    # the same rows always give the same bytes (no timestamp in the gzip header), so git sees no change
    first = (out / "test.rows.csv.gz").read_bytes()
    write_results_csv(read_results_csv(out / "test.rows.csv.gz"), out / "again.csv.gz")
    assert (out / "again.csv.gz").read_bytes() == first
    (out / "again.csv.gz").unlink()
    assert recheck.recheck(out.parent) == []


def test_the_headline_gives_both_banks_with_intervals(results):
    _, out = results
    data = json.loads((out / "headline.json").read_text())
    assert data["banks"] == {"validation": 4711, "test": TEST_SEED}
    assert list(data["policies"]) == ["braking", "oracle", "oracle_brake1"]
    ceiling = data["policies"]["oracle_brake1"]["test"]
    assert ceiling["difference_pts"] <= 0 and ceiling["difference_ci95"][0] <= ceiling["difference_pts"]
    assert data["policies"]["oracle"]["test"]["share"] == 100.0
    text = (out / "headline.md").read_text()
    assert f"test bank: seed {TEST_SEED}" in text and "Planner after 1 frame" in text
    assert data["world_model"] == {"vae_sha": [], "rnn_sha": []}  # scripted policies only: no world model
    # what the run cost, stage by stage, each preset's seeds together
    assert "| agent_r1 | 2 | 5.0–6.0 | 11.0 |" in text and "| **all stages** | 5 |  | 13.5 |" in text


def test_the_pooled_table_pools_the_validation_banks_and_recheck_holds_it(results, tmp_path):
    import shutil

    root, out = results
    text = (out / published.POOLED).read_text()
    assert "validation banks pooled: 4711, 4712" in text and "bank 4712: share %" in text
    planner = next(line for line in text.splitlines() if line.startswith("| Privileged planner"))
    assert "| — | 100.0 | 100.0 | 100.0 |" in planner  # the ceiling is 100 on each bank and pooled
    copy = tmp_path / "x"
    shutil.copytree(out, copy)
    (copy / published.POOLED).write_text(text.replace(planner, planner.replace("| 100.0 | —", "| 99.0 | —")))
    (problem,) = recheck.recheck(copy, root / "ledger.csv")
    assert "pooled.md" in problem


def test_recheck_names_an_edited_number(results, tmp_path):
    import shutil

    root, out = results
    copy = tmp_path / "x"
    shutil.copytree(out, copy)
    tables = (copy / "test.tables.md").read_text()
    line = next(i for i, x in enumerate(tables.splitlines(), 1) if "Straight-line braking" in x and "|" in x)
    original = tables.splitlines()[line - 1]
    edited = original.replace("|", "| 99.9 |", 2).replace("| 99.9 |", "|", 1)  # one cell more, after the name
    (copy / "test.tables.md").write_text(tables.replace(original, edited, 1))
    (problem,) = recheck.recheck(copy, root / "ledger.csv")
    assert f"test.tables.md, line {line} (Straight-line braking)" in problem and "committed 99.9" in problem


def test_recheck_fails_when_the_rows_change_under_a_table(results, tmp_path):
    import shutil

    root, out = results
    copy = tmp_path / "x"
    shutil.copytree(out, copy)
    rows = read_results_csv(copy / "test.rows.csv.gz")
    for r in rows:
        if r["policy"] == "oracle_brake1":
            r["occupant_injury"] = 0.5  # a ceiling that hurts its occupants
    write_results_csv(rows, copy / "test.rows.csv.gz")
    problems = recheck.recheck(copy, root / "ledger.csv")
    assert any("test.tables.md" in p for p in problems) and any("headline.md" in p for p in problems)


def test_recheck_holds_a_published_test_evaluation_to_its_ledger_row(results, tmp_path):
    """The rows of a test-bank evaluation must be the evaluation the ledger recorded: its family, seed and
    experiment, its policies with as many scenarios each; a validation evaluation needs no row."""
    root, out = results
    ledger = (root / "ledger.csv").read_text()
    rows, meta = published.published(out)["test"]
    assert recheck.ledger_problems("test", rows, meta, root / "ledger.csv") == []
    validation_rows, validation_meta = published.published(out)["validation"]
    assert recheck.ledger_problems("validation", validation_rows, validation_meta, None) == []

    def problems(text):
        (tmp_path / "ledger.csv").write_text(text)
        return recheck.ledger_problems("test", rows, meta, tmp_path / "ledger.csv")

    (missing,) = recheck.ledger_problems("test", rows, meta, None)
    assert "no ledger.csv" in missing
    (other,) = problems(ledger.replace(",t,smoke,", ",another,smoke,"))
    assert f"has no row for the porav test bank (seed {TEST_SEED}), experiment 't'" in other
    (count,) = problems(ledger.replace(",6,braking", ",7,braking"))  # 6 scenarios: 2 TTCs x 3 per cell
    assert "braking has 6 rows, the ledger 7 scenarios" in count
    (policies,) = problems(ledger.replace("; oracle_brake1", ""))
    assert "in the rows only: ['oracle_brake1']" in policies


def test_edited_rows_under_tables_rendered_again_are_caught_by_the_ledgers_digest(results, tmp_path):
    """Every table can be rendered again from edited rows, and the row counts and model hashes kept: the digest the
    evaluation wrote into its ledger row still tells."""
    import shutil

    root, out = results
    assert banks.read_ledger(root / "ledger.csv")[-1]["rows_sha"] == recheck.rows_sha(out / "test.rows.csv.gz")
    copy = tmp_path / "x"
    shutil.copytree(out, copy)
    rows = read_results_csv(copy / "test.rows.csv.gz")
    rows[0]["occupant_injury"] = 0.5
    write_results_csv(rows, copy / "test.rows.csv.gz")
    rows, meta = published.published(copy)["test"]
    (copy / "test.tables.md").write_text(published.render_tables(rows, meta))
    published.write_headline(copy)
    (problem,) = recheck.recheck(copy, root / "ledger.csv")
    assert "test: the rows are not the evaluation" in problem and "SHA-256" in problem


def test_the_committed_rows_carry_the_model_hashes_the_ledger_recorded(tmp_path):
    """On the committed headline: the ledger's actor hash of one agent changed, and its rows no longer match."""
    rows, meta = published.published(published.RESULTS / "porav")["test"]
    ledger = (published.RESULTS / "ledger.csv").read_text()
    assert recheck.ledger_problems("test", rows, meta, published.RESULTS / "ledger.csv") == []
    (tmp_path / "ledger.csv").write_text(ledger.replace("actor=03535b7c244d", "actor=000000000000"))
    (problem,) = recheck.ledger_problems("test", rows, meta, tmp_path / "ledger.csv")
    assert "agent_r1/seed0's actor is 03535b7c244d in the rows, 000000000000 in the ledger" in problem


def test_the_readme_table_sits_between_its_markers():
    text = f"intro\n{published.README_BEGIN}\nold table\n{published.README_END}\nrest\n"
    fresh = published.readme_with_table(text, "| new |")
    assert fresh == f"intro\n{published.README_BEGIN}\n| new |\n{published.README_END}\nrest\n"
    with pytest.raises(published.RecheckError, match="markers"):
        published.readme_with_table("no markers", "| new |")


def test_every_committed_table_is_what_its_rows_give():
    """docs/results as committed: every published evaluation and headline recomputes from its rows."""
    assert recheck.recheck(published.RESULTS) == []


def test_every_table_without_rows_says_so_at_its_top():
    """A committed table that ``recheck`` cannot recompute (no rows beside it) says so before anything else, so that
    no reader takes it for a sealed result. The reports (README.md) are read by people and checked by hand."""
    unmarked = []
    for path in sorted(published.RESULTS.rglob("*.md")):
        text = path.read_text()
        if path.name == "README.md" or not re.search(r"^\|\s*-{3}", text, re.M):
            continue
        stem = path.name.removesuffix(published.TABLES)
        if (path.parent / (stem + published.ROWS)).exists():
            continue
        if path.name in ("headline.md", published.POOLED) and any(path.parent.glob("*" + published.ROWS)):
            continue
        if "rows are not committed" not in " ".join(text[:1500].split()):
            unmarked.append(str(path.relative_to(published.RESULTS)))
    assert unmarked == [], f"tables without rows that do not say so: {unmarked}"


def test_every_number_in_a_reports_headline_tables_is_in_its_committed_tables():
    """A report copies its headline tables by hand from the tables its rows give (``*.tables.md``, ``headline.md``):
    every decimal number in the table rows of its "## Headline" section must appear there, so that a slip in the
    copying, or a report left behind by a new publication, fails here."""
    decimal = re.compile(r"[-−]?\d+\.\d+")
    directories = sorted({p.parent for p in published.RESULTS.rglob("*" + published.ROWS)})
    assert directories, "no published rows under docs/results"
    for directory in directories:
        report = (directory / "README.md").read_text()
        assert "\n## Headline" in report, f"{directory}/README.md has no '## Headline' section"
        section = report.split("\n## Headline", 1)[1].split("\n## ", 1)[0]
        tables = [*directory.glob("*" + published.TABLES), *directory.glob("headline.md"), *directory.glob("pooled.md")]
        known = {n.replace("−", "-") for t in tables for n in decimal.findall(t.read_text())}
        quoted = [
            (n, line.split("|")[1].strip())
            for line in section.splitlines()
            if line.startswith("|")
            for n in decimal.findall(line)
        ]
        assert quoted, f"{directory}/README.md: its headline section quotes no table"
        missing = [(n, row) for n, row in quoted if n.replace("−", "-") not in known]
        assert missing == [], f"{directory}/README.md quotes numbers its committed tables do not hold: {missing[:5]}"


def test_a_learner_judged_later_on_its_own_world_model_joins_the_readme_table(tmp_path):
    """A folder under porav/ with its own headline (a learner evaluated later beside braking and the planner) adds
    its learned rows, marked, and not its scripted ones again."""
    porav = tmp_path / "porav"
    (porav / "later").mkdir(parents=True)
    data = json.loads((published.RESULTS / "porav" / "headline.json").read_text())
    (porav / "headline.json").write_text(json.dumps(data))
    learned = {**data["policies"]["agent_r1"], "label": "A later learner"}
    later = {**data, "policies": {p: data["policies"][p] for p in ("braking", "oracle")} | {"agent_x": learned}}
    (porav / "later" / "headline.json").write_text(json.dumps(later))
    table = published.readme_table(tmp_path)
    assert "| A later learner † | 3 | -178.0 [-215.3, -145.4] | -159.3 [-194.9, -131.6] |" in table
    assert table.count("Privileged planner") == 1 and "(docs/results/porav/later/)" in table

    # one judged on another view of the camera (views/VIEW/NAME/) is marked apart, with the view in its label
    (tmp_path / "views/cover64/sealed").mkdir(parents=True)
    (tmp_path / "views/cover64/sealed/headline.json").write_text(json.dumps(later))
    table = published.readme_table(tmp_path)
    assert "| A later learner, view cover64 ‡ | 3 | -178.0 [-215.3, -145.4] | -159.3 [-194.9, -131.6] |" in table
    assert table.count("Privileged planner") == 1 and "(docs/results/views/cover64/sealed/)" in table


def test_the_readme_result_table_is_the_generated_one():
    text = published.README.read_text()
    assert published.readme_with_table(text, published.readme_table()) == text, (
        "README.md's result table differs from docs/results: run `python -m worldmodel.report readme`"
    )


def test_gzip_rows_read_back_like_plain_ones(tmp_path):
    rows = [{"policy": "braking", "scenario_id": 1, "ttc": 0.5, "pedestrian_injury": float("nan")}]
    write_results_csv(rows, tmp_path / "r.csv.gz")
    assert gzip.decompress((tmp_path / "r.csv.gz").read_bytes()).startswith(b"policy,")
    back = read_results_csv(tmp_path / "r.csv.gz")
    assert back[0]["scenario_id"] == 1 and back[0]["pedestrian_injury"] != back[0]["pedestrian_injury"]


def test_the_stage_time_table_leaves_out_unfinished_steps_and_marks_lower_bounds():
    """A step interrupted and not finished has no time yet; one resumed after a part no record timed is marked."""
    timings = {
        "vae": {"wall_s": 120.0, "complete": True, "untimed_part": False},
        "agent_r1": {"wall_s": 300.0},  # a record written before steps said whether they finished
        "agent_r1/seed1": {"wall_s": 600.0, "complete": True, "untimed_part": True},
        "agent_r1/seed2": {"wall_s": 50.0, "complete": False, "untimed_part": False},
    }
    table = "\n".join(published.stage_time_table(timings))
    assert "| vae | 1 | 2.0 | 2.0 |" in table
    assert "| agent_r1 \\* | 2 | 5.0–10.0 | 15.0 |" in table
    assert "| **all stages** | 3 |  | 17.0 |" in table
    assert table.endswith("at least this long.")


@pytest.mark.parametrize("damage", ["short line", "not a number"])
def test_publish_names_the_malformed_file_and_line(results, tmp_path, capsys, damage):
    """A results.csv with a line cut short, or a number that is not one, stops ``report publish`` with one line
    naming the file and the line, and writes nothing."""
    import shutil

    root, _ = results
    copy = tmp_path / "eval"
    shutil.copytree(root / "runs/t/eval", copy)
    lines = (copy / "results.csv").read_text().splitlines()
    cells = lines[3].split(",")
    lines[3] = ",".join(cells[:5]) if damage == "short line" else ",".join([*cells[:4], "fast", *cells[5:]])
    (copy / "results.csv").write_text("\n".join(lines) + "\n")
    assert report_cli.main(["publish", str(copy), str(tmp_path / "out" / "validation"), "--command", "x"]) == 2
    said = capsys.readouterr().out
    assert said.startswith("error: ") and f"{copy / 'results.csv'}, line 4" in said and "Traceback" not in said
    assert not (tmp_path / "out").exists()


def test_publish_refuses_a_folder_not_named_as_an_evaluation(tmp_path):
    """A folder whose name no evaluation folder starts with stops ``report publish`` with exit 2 and one sentence
    naming the folder and the names it takes, not a bare StopIteration; nothing is written."""
    import subprocess
    import sys

    folder = tmp_path / "runs/x/notaneval"
    folder.mkdir(parents=True)
    (folder / "summary.json").write_text("{}")  # finished, so only its name is wrong
    stem = tmp_path / "out" / "validation"
    cmd = [sys.executable, "-m", "worldmodel.report", "publish", str(folder), str(stem), "--command", "x"]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    said = result.stdout + result.stderr
    assert result.returncode == 2, said[-3000:]
    assert "Traceback" not in said and str(folder) in said and "runs/NAME/eval_test" in said, said[-3000:]
    assert not (tmp_path / "out").exists()


def test_recheck_lists_the_tables_it_cannot_hold_to_rows(results, capsys):
    """A table with no rows beside it (an investigation's, kept as rendered) is named as not rechecked, and the
    closing line counts both kinds."""
    _, out = results
    rowless = out / "an_investigation_tables.md"
    rowless.write_text("| policy | share |\n|---|---:|\n| braking | 0.0 |\n")
    try:
        assert report_cli.main(["recheck", str(out.parent)]) == 0
    finally:
        rowless.unlink()
    said = capsys.readouterr().out.splitlines()
    assert f"not rechecked, no rows beside it: {rowless}" in said
    assert said[-1].startswith(f"every table with rows under {out.parent} (3) is what its rows give")
    assert said[-1].endswith("1 tables without rows were not rechecked (listed above)")


def test_recheck_counts_every_policys_rows_so_a_removed_row_is_found(results):
    """One row removed from a validation evaluation leaves its rounded tables as they were; recheck still finds it,
    by the policy whose rows now number fewer than every other's."""
    _, out = results
    path = out / "validation.rows.csv.gz"
    whole = path.read_bytes()
    rows = read_results_csv(path)
    victim = next(i for i, r in enumerate(rows) if r["policy"] == "oracle")
    try:
        write_results_csv(rows[:victim] + rows[victim + 1 :], path)
        problems = recheck.recheck(out.parent)
    finally:
        path.write_bytes(whole)
    assert any("validation: oracle (seed 0) has" in p and "a row was removed or added" in p for p in problems)
    assert recheck.recheck(out.parent) == []


def test_rows_are_held_to_the_models_their_ledger_row_names():
    """A row's model hashes must be those its ledger row names. The one exception: a row that names the experiment's
    world model (a hash the ledger names for another agent of that evaluation) for an agent the ledger records as
    reading none, as rows of the true-state actor preset did before the rows followed a preset's own input."""
    from worldmodel.report.recheck import _ledger_mismatch

    entry = {
        "policies": "braking; agent_r2/seed0 (vae=aaa, rnn=bbb, actor=ccc); agent_r2_t/seed0 (actor=ddd)",
        "scenarios": "1",
    }
    rows = [
        {"policy": "braking", "policy_seed": "", "vae_sha": "", "rnn_sha": "", "actor_sha": ""},
        {"policy": "agent_r2", "policy_seed": 0, "vae_sha": "aaa", "rnn_sha": "bbb", "actor_sha": "ccc"},
        {"policy": "agent_r2_t", "policy_seed": 0, "vae_sha": "", "rnn_sha": "", "actor_sha": "ddd"},
    ]
    assert _ledger_mismatch(rows, entry) is None
    rows[2].update(vae_sha="aaa", rnn_sha="bbb")  # the experiment's world model, which it does not read
    assert _ledger_mismatch(rows, entry) is None
    rows[2].update(vae_sha="eee")  # a world model the evaluation never had
    assert "agent_r2_t/seed0's vae is eee" in _ledger_mismatch(rows, entry)
    rows[2].update(vae_sha="aaa", actor_sha="fff")  # the actor is always held to the ledger
    assert "agent_r2_t/seed0's actor is fff" in _ledger_mismatch(rows, entry)
    rows[2].update(actor_sha="ddd")
    rows[1].update(vae_sha="zzz")  # an agent the ledger names a world model for is held to it
    assert "agent_r2/seed0's vae is zzz" in _ledger_mismatch(rows, entry)
