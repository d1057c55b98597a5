"""The validation bank: the test bank's grid with scenarios of its own, so settings and checkpoints are chosen
without touching the test bank."""

from __future__ import annotations

import pytest

from worldmodel import artifacts, evaluate
from worldmodel.common import StageError
from worldmodel.config import compose, validate


def cfg(*overrides: str):
    return compose("evaluate", ["scale=paper", *overrides])


def test_validation_and_test_banks_share_no_scenario():
    test, validation = evaluate.bank(cfg()), evaluate.bank(cfg("evaluate.bank=validation"))
    assert len(test) == len(validation) == 63 * 20
    # the same cells, in the same order ...
    assert [(e.hazard, e.ttc, e.speed) for e in test] == [(e.hazard, e.ttc, e.speed) for e in validation]
    # ... but no scenario in common: not one spec, not one scene seed
    assert not {e.spec for e in test} & {e.spec for e in validation}
    assert not {e.spec.seed for e in test} & {e.spec.seed for e in validation}
    assert evaluate.bank(cfg()) == test  # and each bank is reproducible


def test_validation_results_go_to_their_own_folder():
    assert artifacts.eval_dir(cfg()).name == "eval"
    assert artifacts.eval_dir(cfg("evaluate.bank=validation")).name == "eval_validation"


@pytest.mark.parametrize(
    "override,key",
    [("evaluate.bank=train", "evaluate.bank"), ("evaluate.validation_seed=2018", "evaluate.validation_seed")],
)
def test_impossible_bank_settings_are_named(override, key):
    with pytest.raises(StageError, match=key):
        validate(cfg(override))
