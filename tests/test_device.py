"""The ``device`` setting: where torch trains and decides. This machine has no GPU, so these tests pin what the CPU
path does and how a CUDA request is refused; the GPU half is measured by ``benchmarks/gpu_check.py``."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from worldmodel import artifacts, train_vae
from worldmodel.common import StageError, resolve_device, to_cpu
from worldmodel.config import compose, validate

pytestmark = pytest.mark.skipif(torch.cuda.is_available(), reason="pins the behaviour of a machine without CUDA")


def test_auto_is_the_cpu_here_and_a_cuda_request_is_refused_naming_the_fix():
    assert resolve_device("auto") == resolve_device("cpu") == torch.device("cpu")
    for setting in ("cuda", "cuda:0", "cuda:3"):
        with pytest.raises(StageError, match=rf"device={setting}: torch sees no CUDA devices .* use device=cpu"):
            resolve_device(setting)
    with pytest.raises(StageError, match="config device='gpu' is impossible: use auto, cpu, cuda or cuda:N"):
        validate(compose("train_vae", ["device=gpu"]))
    with pytest.raises(StageError, match="device=cuda: torch sees no CUDA"):
        validate(compose("train_vae", ["device=cuda"]))


def test_a_cuda_request_stops_the_stage_before_any_work_with_status_2(tmp_path):
    root = [f"paths.data_root={tmp_path}/data", f"paths.runs_root={tmp_path}/runs", "experiment=t", "scale=smoke"]
    done = subprocess.run(
        [sys.executable, "-m", "worldmodel.collect", *root, "device=cuda"], capture_output=True, text=True
    )
    assert done.returncode == 2, done.stderr[-2000:]
    assert "device=cuda" in done.stderr + done.stdout and "device=cpu" in done.stderr + done.stdout
    assert not (tmp_path / "data" / "t" / "rollouts").exists()  # nothing was collected


def test_the_device_never_enters_a_provenance_hash(tmp_path):
    def sha(stage, *overrides):
        cfg = compose("pipeline", [f"paths.runs_root={tmp_path}", f"paths.data_root={tmp_path}", *overrides])
        return artifacts.provenance(cfg, stage)["config"]

    for stage in ("vae", "rnn", "agent", "eval"):
        assert sha(stage) == sha(stage, "device=cpu") == sha(stage, "device=cuda:1")


def test_checkpoints_of_a_cpu_run_are_saved_as_before():
    """``to_cpu`` hands back the very object when every tensor is on the CPU, so a CPU run pickles what it did
    before the setting existed."""
    state = {"model": {"w": torch.ones(2)}, "rounds": [torch.zeros(1), (torch.ones(1), 3)], "step": 4}
    assert to_cpu(state) is state


def test_a_smoke_vae_trained_with_device_cpu_is_the_default_run_bit_for_bit(smoke_builds, tmp_path):
    import shutil

    weights = {}
    for setting in ("auto", "cpu"):
        root = tmp_path / setting
        shutil.copytree(smoke_builds("rollouts"), root)
        paths = [f"paths.data_root={root}/data", f"paths.runs_root={root}/runs", "experiment=t", "scale=smoke"]
        train_vae.run(compose("train_vae", [*paths, "threads=1", f"device={setting}"]))
        weights[setting] = torch.load(root / "runs/t/vae/last.pt", weights_only=False)["model"]
    assert weights["auto"].keys() == weights["cpu"].keys()
    assert all(torch.equal(weights["auto"][k], weights["cpu"][k]) for k in weights["auto"])


def test_the_gpu_check_runs_its_cpu_half(tmp_path):
    """benchmarks/gpu_check.py at a tiny size on the CPU: every measurement is there and positive, in one JSON."""
    import json

    from benchmarks import gpu_check

    gpu_check.main(["--device", "cpu", "--tiny", "--no-pipeline", "--out", str(tmp_path)])
    result = json.loads((tmp_path / "gpu_check.json").read_text())
    assert result["tiny"] and result["device"] == "cpu"
    assert result["vae_frames_per_s"]["cpu"] > 0 and result["lstm_frames_per_s"]["cpu"] > 0
    assert result["ddpg"]["cpu"]["updates_per_s"] > 0 and result["ddpg"]["cpu"]["decisions_per_s"] > 0
    assert "speedup" not in result  # nothing to compare the CPU with
