"""Artifacts that cannot be silently corrupted or raced: a finished run's checkpoints are checked against the digests
it recorded, a dataset's identity is its content (not how long it took), records made before either are read as
written, and an output has one writer at a time. Each error's advice is followed here to show that it works."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from worldmodel import artifacts, loading, pipeline, train_vae
from worldmodel.common import StageError, file_sha256

REPO = Path(__file__).resolve().parent.parent


def change_a_weight(path: Path) -> None:
    """What a careless user or a flaky disk does: one weight changed, the file saved back as a valid checkpoint."""
    state = torch.load(path, weights_only=False)
    name = next(k for k in state["model"] if k.endswith("weight"))
    state["model"][name].view(-1)[:5] += 1.0
    torch.save(state, path)


def plan_row(cfg, step: str) -> dict:
    return next(r for r in pipeline.plan(cfg) if r["step"] == step)


def test_a_checkpoint_changed_after_its_run_finished_is_refused_then_rebuilt_as_advised(stage_cfg, experiment_copy):
    root = experiment_copy("vae")
    cfg = stage_cfg("train_vae", root=root)
    best = artifacts.vae_dir(cfg) / "best.pt"
    assert artifacts.read_provenance(best.parent)["outputs"]["best.pt"] == file_sha256(best)
    assert plan_row(stage_cfg("pipeline", root=root), "vae")["state"] == "complete"

    change_a_weight(best)
    with pytest.raises(StageError, match="not the file its run wrote") as refused:
        loading.load_vae(cfg)
    with pytest.raises(StageError, match="changed since"):
        train_vae.run(stage_cfg("train_vae", "resume=true", root=root))
    row = plan_row(stage_cfg("pipeline", root=root), "vae")
    assert row["state"] == "stale" and any("best.pt" in r and "after its run finished" in r for r in row["reasons"])
    loading.load_vae(stage_cfg("train_vae", "allow_stale=true", root=root))  # loads, with a warning

    # the advice: delete the run's folder and rerun the command it names
    folder = re.search(r"or delete (\S+) and rerun", str(refused.value)).group(1)
    assert Path(folder) == best.parent
    shutil.rmtree(folder)
    train_vae.run(cfg)
    loading.load_vae(cfg)
    assert plan_row(stage_cfg("pipeline", root=root), "vae")["state"] == "complete"


def test_an_unreadable_checkpoint_names_advice_that_works(stage_cfg, experiment_copy):
    root = experiment_copy("vae")
    cfg = stage_cfg("train_vae", root=root)
    best = artifacts.vae_dir(cfg) / "best.pt"
    record = artifacts.read_provenance(best.parent)
    del record["outputs"]  # a run finished before its checkpoints' digests were recorded: nothing to compare
    artifacts.write_provenance(best.parent, record)
    best.write_bytes(b"not a checkpoint" + best.read_bytes()[16:])
    with pytest.raises(StageError, match="cannot be read") as refused:
        loading.load_vae(cfg)
    folder = re.search(r"Delete (\S+) \(the run that wrote it\)", str(refused.value)).group(1)
    shutil.rmtree(folder)
    train_vae.run(cfg)
    loading.load_vae(cfg)


def test_a_dataset_is_its_content_and_older_records_are_read_as_written(stage_cfg, experiment_copy):
    root = experiment_copy("vae")
    cfg = stage_cfg("train_vae", root=root)
    manifest = artifacts.manifest_path(cfg)
    identity = artifacts.rollouts_id(cfg)
    content = manifest.read_text()

    # how long the collection took is not what it holds
    timed = content.replace('"wall_s": ', '"wall_s": 1234').replace(
        '"frames_per_s_this_run": ', '"frames_per_s_this_run": 9'
    )
    assert timed != content
    manifest.write_text(timed)
    assert artifacts.rollouts_id(cfg) == identity
    assert plan_row(stage_cfg("pipeline", root=root), "vae")["state"] == "complete"

    # a record made when a dataset was its manifest's bytes names this dataset: not stale
    vae = artifacts.vae_dir(cfg)
    record = artifacts.read_provenance(vae)
    old = {**record["inputs"], "rollouts": file_sha256(manifest)}
    artifacts.write_provenance(vae, {"inputs": old, "config": record["config"]})
    for name in ("best.pt", "last.pt"):
        state = torch.load(vae / name, weights_only=False)
        torch.save({**state, "provenance": {**state["provenance"], "inputs": old}}, vae / name)
    assert plan_row(stage_cfg("pipeline", root=root), "vae")["state"] == "complete"
    loading.load_vae(cfg)

    # and another dataset is another dataset
    manifest.write_text(content.replace('"episodes": ', '"episodes": 1', 1))
    assert artifacts.rollouts_id(cfg) != identity
    assert plan_row(stage_cfg("pipeline", root=root), "vae")["state"] == "stale"
    with pytest.raises(StageError, match="is stale"):
        loading.load_vae(cfg)


def hold_lock(directory: Path) -> subprocess.Popen:
    """Another process holding ``directory``'s writer lock until it is killed."""
    code = (
        "import sys, time\n"
        "from worldmodel.common import writer_lock\n"
        f"with writer_lock({str(directory)!r}, 'a test'):\n"
        "    print('held', flush=True)\n"
        "    time.sleep(120)\n"
    )
    holder = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    return holder


def test_a_second_writer_is_refused_by_name_and_a_killed_one_leaves_no_lock(stage_cfg, experiment_copy):
    root = experiment_copy("vae")
    cfg = stage_cfg("train_vae", "resume=true", root=root)
    holder = hold_lock(artifacts.vae_dir(cfg))
    try:
        with pytest.raises(StageError, match=rf"being written by another process \(pid {holder.pid}: "):
            train_vae.run(cfg)
    finally:
        holder.kill()
        holder.wait()
    train_vae.run(cfg)  # the kernel dropped the killed holder's lock

    runs = artifacts.runs_root(cfg)
    holder = hold_lock(runs)  # another pipeline on this experiment
    try:
        with pytest.raises(StageError, match=rf"{runs} is being written by another process \(pid {holder.pid}"):
            pipeline.run(stage_cfg("pipeline", root=root))
        assert plan_row(stage_cfg("pipeline", "plan=true", root=root), "vae")["state"] == "complete"  # reading: free
    finally:
        holder.kill()
        holder.wait()


def test_a_finished_agent_resumed_with_nothing_left_to_do_saves_the_same_bytes(stage_cfg, experiment_copy):
    """A launcher's job may start a step that a job before it has just finished: resumed, it has no step left and
    saves its checkpoint again. What it loaded (arrays with dtypes of their own) saves as what it trained, so the
    recorded digest and the evaluation rows' actor hash stay what they were."""
    from worldmodel import train_agent

    root = experiment_copy("rnn")
    cfg = stage_cfg("train_agent", "reward=r1", "agent.total_steps=120", "agent.ddpg.warmup_steps=60", root=root)
    train_agent.run(cfg)
    last = artifacts.AgentId.of(cfg).dir(cfg) / "last.pt"
    before = file_sha256(last)
    train_agent.run(
        stage_cfg(
            "train_agent", "reward=r1", "agent.total_steps=120", "agent.ddpg.warmup_steps=60", "resume=true", root=root
        )
    )
    assert file_sha256(last) == before
    assert artifacts.changed_outputs(last.parent) == []
