"""The banks: one validation bank after another for choosing, one sealed test bank per family for final numbers,
and the ledger that records every evaluation on a test bank."""

from __future__ import annotations

import importlib
import re
from types import SimpleNamespace

import pytest

from worldmodel import artifacts, banks, evaluate, registry
from worldmodel.common import StageError
from worldmodel.config import compose, validate
from worldmodel.families.chae import system as chae
from worldmodel.families.kim import system as kim
from worldmodel.families.merola import system as merola
from worldmodel.families.porav import evaluation as porav_eval


def cfg(*overrides: str):
    return compose("evaluate", ["scale=paper", *overrides])


def test_the_paper_test_bank_shares_no_scenario_with_any_validation_bank():
    test = porav_eval.bank(cfg("evaluate.bank=test"))
    assert len(test) == 63 * 20
    assert porav_eval.bank(cfg("evaluate.bank=test")) == test  # reproducible
    for seed in banks.validation_seeds("porav"):
        validation = porav_eval.bank(cfg(f"evaluate.validation_seed={seed}"))
        # the same cells, in the same order, but not one spec and not one scene seed in common
        assert [(e.hazard, e.ttc, e.speed) for e in test] == [(e.hazard, e.ttc, e.speed) for e in validation]
        assert not {e.spec for e in test} & {e.spec for e in validation}
        assert not {e.spec.seed for e in test} & {e.spec.seed for e in validation}


@pytest.mark.parametrize("family,module", [("chae", chae), ("kim", kim), ("merola", merola)])
def test_each_peer_test_draw_is_new(family, module):
    """The peers' banks draw their fields from the seed: the test draw repeats none of a validation draw's trials."""
    c = compose("evaluate", [f"evaluate.family={family}", f"evaluate.{family}.trials=20"]).evaluate[family]

    def trials(seed):
        specs = module.bank(SimpleNamespace(**{**dict(c), "seed": seed}))
        return [repr(s) for s in specs]

    test = trials(banks.test_seed(family))
    assert len(test) == len(set(test)) > 0
    for seed in banks.validation_seeds(family):
        assert not set(test) & set(trials(seed)), seed


def test_each_bank_writes_its_own_folder():
    names = {
        (): "eval",
        ("evaluate.bank=test",): "eval_test",
        ("evaluate.validation_seed=4712",): "eval_seed4712",
        ("evaluate.family=kim",): "eval_kim",
        ("evaluate.family=kim", "evaluate.bank=test"): "eval_kim_test",
        ("evaluate.family=merola", "evaluate.merola.seed=77"): "eval_merola_seed77",
    }
    for overrides, name in names.items():
        assert artifacts.eval_dir(cfg(*overrides)).name == name


@pytest.mark.parametrize(
    "override,key",
    [
        (f"evaluate.validation_seed={banks.test_seed('porav')}", "evaluate.validation_seed"),
        (f"evaluate.kim.seed={banks.test_seed('kim')}", "evaluate.kim.seed"),
        (f"evaluate.chae.seed={banks.test_seed('porav')}", "evaluate.chae.seed"),  # any family's test seed
        (f"agent.chae.select.seed={banks.test_seed('chae')}", "agent.chae.select.seed"),  # Chae's checkpoint selection
    ],
)
def test_a_test_seed_is_refused_as_a_validation_draw(override, key):
    """Also any other family's test seed: a draw that is some family's sealed bank is never for choosing."""
    with pytest.raises(StageError, match=rf"config {re.escape(key)}=\d+ is impossible: .* sealed test seed"):
        validate(cfg(override))


def test_an_unknown_bank_is_named():
    with pytest.raises(StageError, match="evaluate.bank='train' is impossible: it must be one of validation, test"):
        validate(cfg("evaluate.bank=train"))
    with pytest.raises(StageError, match="banks"):
        validate(compose("pipeline", ["banks=[validation,final]"]))


def test_the_ledger_appends_and_counts(tmp_path):
    path = tmp_path / "docs" / "ledger.csv"
    assert banks.uses("porav", path=path) == 0 and banks.read_ledger(path) == []
    for figure in ("share 40.0 %", "share 41.0 %"):
        banks.record(
            path,
            experiment="e",
            scale="paper",
            family="porav",
            scenarios=1260,
            policies={"braking": {}, "agent_r2/seed0": {"vae": "aa", "rnn": "bb", "actor": "cc"}},
            headline={"agent_r2": figure},
        )
    banks.record(path, experiment="e", scale=None, family="kim", scenarios=5, policies={}, headline={})
    rows = banks.read_ledger(path)
    assert path.read_text().count("date,commit") == 1  # one header
    assert [r["headline"] for r in rows[:2]] == ["agent_r2: share 40.0 %", "agent_r2: share 41.0 %"]
    assert rows[0]["policies"] == "braking; agent_r2/seed0 (vae=aa, rnn=bb, actor=cc)"
    assert rows[0]["bank_seed"] == str(banks.test_seed("porav")) and rows[0]["commit"]
    assert banks.uses("porav", path=path) == 2 and banks.uses("kim", path=path) == 1
    assert banks.uses("merola", path=path) == 0


def test_a_ledger_from_before_a_column_gets_it_and_keeps_its_rows(tmp_path):
    path = tmp_path / "ledger.csv"
    old_columns = [c for c in banks.LEDGER_COLUMNS if c != "rows_sha"]
    earlier = '2026-01-01T00:00:00Z,abc,e,paper,porav,1,3,braking,"braking: risk 1.00 %"'
    path.write_text(",".join(old_columns) + "\n" + earlier + "\n")
    banks.record(path, experiment="e", scale=None, family="kim", scenarios=5, policies={}, headline={}, rows_sha="f0")
    first, second = banks.read_ledger(path)
    assert path.read_text().splitlines()[0] == ",".join(banks.LEDGER_COLUMNS)
    assert first == {
        **dict(
            zip(
                old_columns,
                ["2026-01-01T00:00:00Z", "abc", "e", "paper", "porav", "1", "3", "braking", "braking: risk 1.00 %"],
            )
        ),
        "rows_sha": "",
    }
    assert second["rows_sha"] == "f0" and second["family"] == "kim"


def test_evaluating_the_test_bank_records_itself_and_a_validation_bank_does_not(stage_cfg, tmp_path):
    """The real stage on a tiny grid: a validation evaluation leaves the ledger alone, each test evaluation adds a
    row with its policies and headline figures."""
    tiny = ["evaluate.ttcs=[1.0]", "evaluate.speeds=[10.0]", "evaluate.hazards=[pedestrian]", "evaluate.per_cell=2"]
    ledger = tmp_path / "ledger.csv"
    evaluate.run(stage_cfg("evaluate", *tiny, "evaluate.num_workers=1"))
    assert not ledger.exists()
    c = stage_cfg("evaluate", *tiny, "evaluate.num_workers=1", "evaluate.bank=test")
    evaluate.run(c)
    with pytest.raises(StageError, match="already judged experiment 't'.*evaluate.retest=true"):
        evaluate.run(c)  # a second look at the sealed bank is refused before anything runs
    assert len(banks.read_ledger(ledger)) == 1
    evaluate.run(stage_cfg("evaluate", *tiny, "evaluate.num_workers=1", "evaluate.bank=test", "evaluate.retest=true"))
    rows = banks.read_ledger(ledger)
    assert len(rows) == 2 and banks.uses("porav", path=ledger) == 2
    assert rows[0]["family"] == "porav" and rows[0]["scenarios"] == "2" and rows[0]["scale"] == "smoke"
    assert rows[0]["policies"] == "braking; oracle"
    assert rows[0]["headline"].startswith("braking: risk ") and "oracle: risk " in rows[0]["headline"]
    assert (tmp_path / "runs" / "t" / "eval_test" / "summary.json").exists()
    assert (tmp_path / "runs" / "t" / "eval" / "summary.json").exists()


def test_an_evaluation_is_judged_again_only_when_its_own_settings_change(tmp_path):
    """Another family's settings do not enter an evaluation's provenance, so changing them never sends the paper's
    family back to its test bank (a second ledger row for the same configuration)."""

    def sha(*overrides):
        c = compose("evaluate", [f"paths.runs_root={tmp_path}", "evaluate.bank=test", *overrides])
        return artifacts.provenance(c, "eval")["config"]

    assert sha() == sha("evaluate.kim.trials=7") == sha("evaluate.chae.seed=99") == sha("evaluate.num_workers=1")
    assert sha() != sha("evaluate.per_cell=7")
    kim = ("evaluate.family=kim",)
    assert sha(*kim) == sha(*kim, "evaluate.merola.trials=7") != sha(*kim, "evaluate.kim.trials=7")


@pytest.mark.parametrize(
    "module,args",
    [
        ("chae_split", ["runs/x", "--seeds", "0", "1", "2", "--draw", "88384"]),
        ("chae_detector", ["--thresholds", "1.0", "--draw", "88384"]),
        ("chae_margin", ["runs/x", "--seeds", "0", "--margins", "0", "--draw", "88384"]),
        ("chae_reselect", ["runs/x", "--seeds", "0", "--out", "runs/y", "--draw", "88384"]),
        ("chooser_floor", ["--validation-seeds", "4711,56171"]),
    ],
)
def test_the_experiments_refuse_a_sealed_draw(module, args, capsys):
    """The investigations' scripts choose settings, so a sealed test seed is refused before any work."""
    main = importlib.import_module(f"experiments.{module}").main
    with pytest.raises(SystemExit) as stop:
        main(args)
    assert stop.value.code == 2
    assert "is a sealed test seed: choose a validation draw" in capsys.readouterr().err


def test_the_suite_never_draws_a_sealed_test_bank():
    """Under the test suite the test banks come from test-only seeds, and a real sealed seed, however it is asked
    for, is an error: so no test evaluates on a real test bank."""
    families = registry.families()
    suite = {f.suite_test_seed for f in families}
    assert banks.IN_TEST_SUITE and all(banks.test_seed(f.name) == f.suite_test_seed for f in families)
    assert not suite & banks.sealed_seeds() and banks.sealed_seeds() == {f.sealed_seed for f in families}
    assert not suite & {s for f in families for s in f.validation_seeds}
    for f in families:
        assert banks.draw_seed("test", f.name, 4711) == f.suite_test_seed
        with pytest.raises(RuntimeError, match=f"sealed test seed {f.sealed_seed}"):
            banks.draw_seed("validation", f.name, f.sealed_seed)
        assert banks.sealed_seed_problem(f.sealed_seed) and banks.sealed_seed_problem(f.suite_test_seed)
