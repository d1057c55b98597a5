"""SIGTERM during training saves a checkpoint and exits cleanly; resume=true then finishes the job exactly."""
from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import torch

from worldmodel import collect, train_vae

REPO = Path(__file__).resolve().parent.parent


def test_sigterm_mid_epoch_then_resume_equals_uninterrupted(stage_cfg, tmp_path):
    collect.run(stage_cfg("collect"))
    overrides = ["vae.batch_size=4", "threads=1"]
    cmd = [sys.executable, "-m", "worldmodel.train_vae", f"paths.data_root={tmp_path}/data",
           f"paths.runs_root={tmp_path}/runs", "experiment=t", "scale=smoke", "vae.epochs=200", *overrides]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out = tmp_path / "runs/t/vae"
    deadline = time.time() + 120
    while not list(out.glob("events.out.tfevents.*")) and time.time() < deadline:
        time.sleep(0.1)
    time.sleep(1.5)   # let it train a little past the first epoch boundary or two
    proc.send_signal(signal.SIGTERM)
    log, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0, log
    assert "SIGTERM received" in log and "stopped at step" in log
    state = torch.load(out / "last.pt", weights_only=False)
    stopped_epoch, stopped_step = state["epoch"], state["step"]
    assert 0 < stopped_step and stopped_epoch < 200
    assert state["batch_in_epoch"] > 0, "the stop should land inside an epoch"

    # Finish the interrupted epoch with resume=true, and compare with a run that was never interrupted.
    target = stopped_epoch + 1
    train_vae.run(stage_cfg("train_vae", *overrides, f"vae.epochs={target}", "resume=true"))
    resumed = torch.load(out / "last.pt", weights_only=False)
    assert resumed["epoch"] == target and resumed["step"] >= stopped_step

    straight = tmp_path / "straight"
    collect.run(stage_cfg("collect", root=straight))
    train_vae.run(stage_cfg("train_vae", *overrides, f"vae.epochs={target}", root=straight))
    ref = torch.load(straight / "runs/t/vae/last.pt", weights_only=False)
    assert ref["step"] == resumed["step"]
    for k, v in ref["model"].items():
        assert torch.allclose(v, resumed["model"][k], atol=1e-6), k
