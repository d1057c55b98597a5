"""A checkpoint cannot run code: a file that names a function to call while it is unpickled is refused unread by
every loader, the file and the name in the error, even when its digest in ``provenance.json`` was updated to match
(worldmodel/checkpoints.py). Each test fails against a loader that unpickles in full: the command runs."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from worldmodel import artifacts, checkpoints, train_agent, train_rnn, train_vae
from worldmodel.artifacts import AgentId
from worldmodel.common import StageError, atomic_torch_save, file_sha256, rng_state

REPO = Path(__file__).resolve().parent.parent


class RunsCommand:
    """What an attacker adds to a checkpoint: unpickling it calls ``os.system``."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def poison(path: Path, marker: Path) -> None:
    """The attack in full: the payload added to a real checkpoint, and the digest its run recorded updated to match,
    as whoever hands over a run folder can."""
    state = checkpoints.read_checkpoint(path)
    state["note"] = RunsCommand(marker)
    torch.save(state, path)
    record = artifacts.read_provenance(path.parent) or {}
    if path.name in (record.get("outputs") or {}):
        record["outputs"][path.name] = file_sha256(path)
        artifacts.write_provenance(path.parent, record)


def assert_refused(path: Path, marker: Path, call, *args) -> None:
    with pytest.raises(StageError) as refused:
        call(*args)
    assert str(path) in str(refused.value) and "posix.system" in str(refused.value), refused.value
    assert not marker.exists(), "the checkpoint's command ran"


def test_a_project_checkpoint_reads_back_equal_and_a_payload_is_refused_unread(tmp_path):
    state = {
        "model": torch.nn.Linear(3, 2).state_dict(),
        "rng": rng_state(),  # numpy's RNG state holds an array
        "replay": {"obs": np.arange(12, dtype=np.float32).reshape(4, 3), "done": np.zeros(4, np.uint8)},
        "best": np.float64(0.25),
        "curve": [(1, 0.5), (2, 0.75)],
    }
    atomic_torch_save(state, tmp_path / "last.pt")
    back = checkpoints.read_checkpoint(tmp_path / "last.pt")
    assert torch.equal(back["model"]["weight"], state["model"]["weight"]) and back["curve"] == state["curve"]
    assert back["best"] == state["best"] and type(back["best"]) is np.float64
    assert all(
        np.array_equal(back["replay"][k], v) and back["replay"][k].dtype == v.dtype for k, v in state["replay"].items()
    )
    assert np.array_equal(back["rng"]["numpy"][1], state["rng"]["numpy"][1])

    marker = tmp_path / "ran"
    poison(tmp_path / "last.pt", marker)
    assert_refused(tmp_path / "last.pt", marker, checkpoints.read_checkpoint, tmp_path / "last.pt")
    # an object array, whose items could be anything, is refused too
    torch.save({"a": np.array([1, "x"], dtype=object)}, tmp_path / "objects.pt")
    with pytest.raises(StageError, match="objects.pt"):
        checkpoints.read_checkpoint(tmp_path / "objects.pt")


def test_the_world_model_is_refused_by_its_loaders_and_its_stages(stage_cfg, experiment_copy):
    from worldmodel import loading

    root = experiment_copy("rnn")
    cfg = stage_cfg("train_rnn", root=root)
    vae, rnn = artifacts.vae_dir(cfg), artifacts.rnn_dir(cfg)
    # resuming a training run reads its last checkpoint (before the best ones are poisoned: the LSTM reads the VAE)
    for stage, run, path in (
        ("train_vae", train_vae.run, vae / "last.pt"),
        ("train_rnn", train_rnn.run, rnn / "last.pt"),
    ):
        marker = root / f"ran-{stage}"
        poison(path, marker)
        assert_refused(path, marker, run, stage_cfg(stage, "resume=true", root=root))

    for which, path, load in ((0, rnn / "best.pt", loading.load_rnn), (1, vae / "best.pt", loading.load_vae)):
        marker = root / f"ran-{which}"
        poison(path, marker)
        assert_refused(path, marker, load, cfg)

    # as a user meets it: the next stage, which reads the VAE, stops with exit 2, the file named, no traceback
    proc = subprocess.run(
        [sys.executable, "-m", "worldmodel.train_rnn", f"paths.data_root={root}/data", f"paths.runs_root={root}/runs"]
        + ["experiment=t", "scale=smoke", "threads=1", "resume=true"],
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    said = proc.stdout + proc.stderr  # a stage logs its error
    assert proc.returncode == 2 and str(vae / "best.pt") in said and "Traceback" not in said, said
    assert not list(root.glob("ran-*")), "a checkpoint's command ran"


# Each learner at the smallest budget that leaves a finished run: its last.pt is what resume and evaluation read.
LEARNERS = {
    "ddpg": ("reward=r1", "agent.total_steps=120"),
    "chooser": (
        *("reward=r2", "agent=chooser", "agent.chooser.episodes=4", "agent.chooser.steers=[1.0]"),
        *("agent.chooser.lane_change_s=[0.3]", "agent.chooser.decide_s=0.5", "agent.chooser.steps=20"),
        *("agent.chooser.batch_size=16", "agent.chooser.num_workers=1"),
    ),
    "counterfactual": ("reward=r2", "agent=counterfactual"),
    "chae": ("agent=dqn_chae", "agent.dqn.warmup_steps=40", "agent.total_steps=120"),
    "merola": ("agent=ddqn_merola", "agent.dqn.warmup_steps=40", "agent.total_steps=120"),
    "kim": ("agent=ddpg_kim", "agent.total_steps=120"),
}


@pytest.mark.parametrize("learner", sorted(LEARNERS))
def test_each_learner_and_family_agent_refuses_a_payload(learner, stage_cfg, experiment_copy):
    """The fit resumed, and the family's agent loaded as its evaluation loads it."""
    from worldmodel import loading

    root = experiment_copy("rnn")
    cfg = stage_cfg("train_agent", *LEARNERS[learner], root=root)
    train_agent.run(cfg)
    agent = AgentId.of(cfg)
    last = agent.dir(cfg) / "last.pt"
    marker = root / "ran"
    poison(last, marker)
    assert_refused(
        last, marker, train_agent.run, stage_cfg("train_agent", *LEARNERS[learner], "resume=true", root=root)
    )
    assert_refused(last, marker, loading.load_agent_state, cfg, agent, "last")


def test_no_loader_unpickles_in_full():
    """No code reads a pickle with everything allowed: the project's own reading goes through read_checkpoint."""
    found = subprocess.run(
        ["grep", "-rnE", r"weights_only=False|pickle\.loads?\(|allow_pickle=True", "worldmodel", "envs", "experiments"],
        capture_output=True,
        text=True,
        cwd=REPO,
    ).stdout
    assert found == "", found


def numpy1_checkpoint(path: Path) -> None:
    """A checkpoint as numpy 1 wrote it: its arrays built by ``numpy.core.multiarray._reconstruct``, a name this
    project's numpy no longer writes, so the safe loader refuses it."""
    import zipfile

    new = path.with_suffix(".numpy2")
    torch.save({"w": torch.ones(2), "replay": np.arange(3)}, new)
    with zipfile.ZipFile(new) as src, zipfile.ZipFile(path, "w") as dst:
        for info in src.infolist():
            data = src.read(info.filename)
            if info.filename.endswith("data.pkl"):
                data = data.replace(b"numpy._core.multiarray\n", b"numpy.core.multiarray\n")
            dst.writestr(info, data)
    new.unlink()


def test_check_lists_what_is_refused_and_trust_rewrites_only_what_it_is_told(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    atomic_torch_save({"w": torch.ones(2)}, run / "best.pt")
    numpy1_checkpoint(run / "last.pt")
    artifacts.write_provenance(run, {"outputs": {"last.pt": file_sha256(run / "last.pt")}})
    assert checkpoints.main(["check", str(run)]) == 2
    out = capsys.readouterr().out
    assert "best.pt: reads safely" in out and "last.pt: REFUSED" in out and "numpy.core.multiarray._reconstruct" in out

    # trust needs every name it builds named; then the file holds the same data, reads safely, and its run's record
    # follows it
    assert checkpoints.main(["trust", str(run / "last.pt"), "--allow", "numpy.ndarray"]) == 2
    assert "numpy.core.multiarray._reconstruct" in capsys.readouterr().err
    assert checkpoints.main(["trust", str(run / "last.pt"), "--allow", "numpy.core.multiarray._reconstruct"]) == 0
    back = checkpoints.read_checkpoint(run / "last.pt")
    assert np.array_equal(back["replay"], np.arange(3)) and torch.equal(back["w"], torch.ones(2))
    assert artifacts.read_provenance(run)["outputs"]["last.pt"] == file_sha256(run / "last.pt")

    # a name that builds an object, not plain data, stays refused even when trusted: rewriting cannot make it safe
    torch.save({"where": Path("/tmp")}, run / "path.pt")
    assert checkpoints.main(["trust", str(run / "path.pt"), "--allow", "pathlib.PosixPath"]) == 2
    assert "not plain data" in capsys.readouterr().err
    # and so does a type no name stands for (a date's dtype), with nothing rewritten
    torch.save({"when": np.datetime64(0, "D")}, run / "date.pt")
    before = (run / "date.pt").read_bytes()
    assert checkpoints.main(["trust", str(run / "date.pt"), "--allow", "numpy.ndarray"]) == 2
    assert "DateTime64DType" in capsys.readouterr().err and (run / "date.pt").read_bytes() == before
