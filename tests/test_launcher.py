"""The launcher's jobs (worldmodel/launcher.py) through submitit's local executor, on the real collection stage: a job
that fails stops the run naming its log, and once the cause is gone the same launch finishes. The whole pipeline
through the launcher is in test_pipeline.py."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from worldmodel import artifacts, collect, launcher
from worldmodel.common import StageError
from worldmodel.pipeline import Step


def test_a_failed_job_names_its_log_and_a_rerun_finishes(stage_cfg, tmp_path):
    cfg = OmegaConf.merge(stage_cfg("collect", "launcher=local"), {"resume": True})
    blocker = tmp_path / "data"
    blocker.write_text("a file where the data folder goes")  # the job cannot make its folder
    step = Step("collect", "collect", collect.run)
    recorded = []

    def launch():
        return launcher.launch(cfg, [step], lambda s: cfg, lambda s, outcome: recorded.append(outcome))

    with pytest.raises(StageError, match=r"job for collect \(log: \S+/runs/t/launcher/\d+_0_log\.err\) failed"):
        launch()
    assert recorded == []
    logs = sorted((tmp_path / "runs/t/launcher").glob("*_0_log.err"))
    assert len(logs) == 1 and "data" in logs[0].read_text()
    blocker.unlink()
    assert launch() is True
    assert artifacts.manifest_path(cfg).exists() and len(recorded) == 1 and not recorded[0]["stopped"]
    assert recorded[0]["wall_s"] > 0 and recorded[0]["peak_rss_mb"] > 0


def test_a_job_that_starts_after_its_step_was_finished_elsewhere_leaves_it_alone(tmp_path):
    """A job a killed launcher submitted can start after the next launcher's job for the same step has finished
    it: it finds the step's completion marker under the step's lock, and skips the stage instead of resuming a
    finished run over the bytes the other job wrote."""
    output = tmp_path / "runs/t/agent_r2_chooser/seed0"
    output.mkdir(parents=True)
    (output / "metrics.json").write_text("{}")
    (output / "last.pt").write_bytes(b"the finished run's checkpoint")

    def stage(cfg):
        raise AssertionError("the stage ran on a finished step")

    outcome = launcher.run_step(stage, None, None, output, output / "metrics.json")
    assert outcome["skipped"] and not outcome["stopped"]
    assert (output / "last.pt").read_bytes() == b"the finished run's checkpoint"
    (output / "metrics.json").unlink()  # unfinished: the job runs its stage
    with pytest.raises(AssertionError, match="the stage ran"):
        launcher.run_step(stage, None, None, output, output / "metrics.json")
