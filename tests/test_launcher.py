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
