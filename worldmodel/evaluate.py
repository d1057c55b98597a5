"""Evaluation on a family's seeded bank: every scripted policy it names and every agent trained on it.

    python -m worldmodel.evaluate experiment=NAME scale=... [evaluate.family=F] [evaluate.bank=test]

``evaluate.family`` picks the scenario family (the paper's when unset; worldmodel/registry.py lists them), whose
own evaluation (``System.evaluate``, e.g. worldmodel/families/porav/evaluation.py) draws its bank, runs the policies,
writes the rows, the summary and the tables under ``runs/NAME/eval[_<family>][_test]/``, and records a test-bank
evaluation in the ledger (worldmodel/banks.py). A sealed test bank judges an experiment once: this command refuses
a second evaluation there unless ``evaluate.retest=true``.
"""

from __future__ import annotations

from . import artifacts, registry
from .banks import sealed_bank_problem
from .common import StageError, set_threads, writer_lock
from .config import hydra_main, validate

NCAP = "ncap"  # the Euro NCAP protocol: an env family with its own command, not a bank of this one


def run(cfg) -> dict:
    typed = validate(cfg)
    set_threads(1)  # one decision at a time: a single thread is fastest for batch-1 inference
    sealed = sealed_bank_problem(cfg, typed.evaluate.family)
    if sealed:
        raise StageError(sealed)
    if typed.evaluate.family == NCAP:
        raise StageError(
            f"the Euro NCAP bank is its own command: python -m worldmodel.ncap experiment={typed.experiment}"
        )
    with writer_lock(artifacts.eval_dir(cfg), "one evaluation"):
        return registry.system(typed.evaluate.family).evaluate(cfg)


main = hydra_main("evaluate")(run)

if __name__ == "__main__":
    main()
