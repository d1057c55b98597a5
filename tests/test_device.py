"""The ``device`` setting: where torch trains and decides. This machine has no GPU, so these tests pin what the CPU
path does and how a CUDA request is refused; the GPU half is measured by ``benchmarks/gpu_check.py``."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

from worldmodel import artifacts, loading, train_vae
from worldmodel.common import StageError, resolve_device, resolve_loader_workers, resolve_workers, to_cpu, usable_cores
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


def run_stage(tmp_path, stage: str, *overrides: str) -> tuple[int, str]:
    """(exit status, output) of ``python -m worldmodel.<stage>`` at smoke scale in ``tmp_path``."""
    root = [f"paths.data_root={tmp_path}/data", f"paths.runs_root={tmp_path}/runs", "experiment=t", "scale=smoke"]
    done = subprocess.run(
        [sys.executable, "-m", f"worldmodel.{stage}", *root, *overrides], capture_output=True, text=True
    )
    return done.returncode, done.stderr + done.stdout


def test_a_cuda_request_stops_the_stage_before_any_work_with_status_2(tmp_path):
    status, output = run_stage(tmp_path, "collect", "device=cuda")
    assert status == 2, output[-2000:]
    assert "device=cuda" in output and "device=cpu" in output
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
    assert result["decisions_per_s"]["cpu"] > 0  # the whole decision: frame, world model and actor
    assert result["vae_frames_per_s"]["cpu_2_threads"] > 0 and result["lstm_frames_per_s"]["cpu_2_threads"] > 0
    assert "speedup" not in result  # nothing to compare the CPU with
    # the GPU's batch (scale=paper_gpu), which only a CUDA run measures: one step of each on the CPU here
    import torch

    from worldmodel.config import compose

    gpu_cfg = compose("pipeline", ["scale=paper_gpu"])
    cpu = torch.device("cpu")
    assert gpu_check.vae_frames_per_s(gpu_cfg, cpu, 1, 0) > 0 and gpu_check.lstm_frames_per_s(gpu_cfg, cpu, 1, 0) > 0


def test_the_new_settings_are_refused_naming_the_key_and_the_fix():
    for override, message in (
        ("amp=fp16", "config amp='fp16' is impossible: use off or bf16"),
        ("amp=bf16", "amp=bf16 runs on a CUDA device only, and this run's device is cpu: use amp=off"),
        ("loader_workers=-1", "config loader_workers=-1 is impossible: use auto or a number >= 0"),
        ("decision_device=gpu", "config decision_device='gpu' is impossible: use auto, cpu, cuda or cuda:N"),
        ("decision_device=cuda", "decision_device=cuda: torch sees no CUDA .* use decision_device=cpu"),
        ("collect.num_workers=0", "config collect.num_workers=0 is impossible: it must be a positive integer or auto"),
        ("evaluate.num_workers=many", "config evaluate.num_workers='many' is impossible: .* or auto"),
        ("agent.chooser.num_workers=-2", "config agent.chooser.num_workers=-2 is impossible: .* or auto"),
        ("demos.num_workers=0", "config demos.num_workers=0 is impossible: .* or auto"),
    ):
        with pytest.raises(StageError, match=message):
            validate(compose("pipeline", [override]))
    typed = validate(compose("pipeline", ["amp=off", "loader_workers=3", "decision_device=auto"]))
    assert (typed.amp, typed.loader_workers, typed.decision_device) == ("off", 3, "auto")


def test_amp_bf16_on_the_cpu_stops_the_stage_with_status_2(tmp_path):
    status, output = run_stage(tmp_path, "train_vae", "amp=bf16")
    assert status == 2, output[-2000:]
    assert "amp=bf16" in output and "amp=off" in output


def test_auto_worker_counts_are_the_usable_cores():
    assert usable_cores() >= 1 and resolve_workers("auto") == usable_cores() and resolve_workers(3) == 3
    typed = validate(compose("pipeline", ["scale=paper"]))
    for section in (typed.collect, typed.demos, typed.evaluate, typed.agent.chooser):
        assert section.num_workers == "auto" and resolve_workers(section.num_workers) >= 1
    cpu = torch.device("cpu")
    assert resolve_loader_workers("auto", cpu) == 0 and resolve_loader_workers(2, cpu) == 2
    assert 0 <= resolve_loader_workers("auto", torch.device("cuda")) <= 4


def test_no_worker_count_amp_or_loader_setting_enters_a_provenance_hash(tmp_path):
    def sha(stage, *overrides):
        cfg = compose("pipeline", [f"paths.runs_root={tmp_path}", f"paths.data_root={tmp_path}", *overrides])
        return artifacts.provenance(cfg, stage)["config"]

    settings = (
        "amp=bf16",
        "loader_workers=3",
        "decision_device=cuda",
        "collect.num_workers=7",
        "demos.num_workers=auto",
        "evaluate.num_workers=5",
        "agent.chooser.num_workers=auto",
    )
    for stage in ("vae", "rnn", "agent", "eval"):
        assert sha(stage) == sha(stage, *settings)
    chooser = ("agent=chooser",)
    assert sha("agent", *chooser, "agent.chooser.num_workers=1") == sha(
        "agent", *chooser, "agent.chooser.num_workers=auto"
    )


def test_loader_workers_read_the_same_batches_in_the_same_order(smoke_builds):
    """The DataLoader path gives what the training process reads itself: the same frames, the same order."""
    from worldmodel.data import iter_frame_batches, loaded_frame_batches

    store = loading.open_rollouts(
        compose("train_vae", [f"paths.data_root={smoke_builds('rollouts')}/data", "experiment=t", "scale=smoke"])
    )
    episodes = store.episodes("train")
    read = list(iter_frame_batches(store, episodes, 16, np.random.default_rng(7), block=8, buffer_blocks=3))
    loaded = list(
        loaded_frame_batches(
            store, episodes, 16, np.random.default_rng(7), 2, pin_memory=False, block=8, buffer_blocks=3
        )
    )
    assert len(read) == len(loaded) > 1
    assert all(np.array_equal(a, b.numpy()) for a, b in zip(read, loaded))


def test_a_smoke_vae_trained_through_loader_workers_is_the_default_run_bit_for_bit(smoke_builds, tmp_path):
    import shutil

    weights = {}
    for workers in (0, 2):
        root = tmp_path / str(workers)
        shutil.copytree(smoke_builds("rollouts"), root)
        paths = [f"paths.data_root={root}/data", f"paths.runs_root={root}/runs", "experiment=t", "scale=smoke"]
        train_vae.run(compose("train_vae", [*paths, "threads=1", f"loader_workers={workers}"]))
        weights[workers] = torch.load(root / "runs/t/vae/last.pt", weights_only=False)["model"]
    assert all(torch.equal(weights[0][k], weights[2][k]) for k in weights[0])


def test_the_gpu_scale_is_the_paper_scale_with_larger_batches_and_its_own_hashes(tmp_path):
    from worldmodel.config import agent_preset

    paths = [f"paths.runs_root={tmp_path}", f"paths.data_root={tmp_path}"]
    paper, gpu = (compose("pipeline", [f"scale={s}", *paths]) for s in ("paper", "paper_gpu"))
    assert (gpu.vae.batch_size, gpu.rnn.batch_size) == (256, 256) and gpu.collect.episodes == paper.collect.episodes
    assert agent_preset(gpu, "chooser").total_steps == agent_preset(paper, "chooser").total_steps == 40000
    for stage in ("vae", "rnn"):  # another batch trains another model
        assert artifacts.provenance(gpu, stage)["config"] != artifacts.provenance(paper, stage)["config"]
