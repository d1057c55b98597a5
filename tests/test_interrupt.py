"""Interrupted training loses at most the work since the last checkpoint, and resume=true finishes the job.

* SIGTERM or SIGINT (Ctrl-C): the stage saves a checkpoint where it is, exits with status 0 and says how to
  resume; resume=true continues (for the VAE, to exactly the weights of an uninterrupted run).
* SIGKILL (kill -9 of the process group, no chance to save): ``last.pt`` is still readable, because
  checkpoints are written atomically, and holds the last periodic checkpoint; resume=true continues from it.

Training runs in a subprocess of its own process group. Signals are timed by watching the stage's progress bar
and its checkpoint files, never by sleeping a fixed time, so the tests hold on a slow, busy machine. A separate
test kills a process that only writes checkpoints at a random point inside a save (a non-atomic save fails it
most of the time), and one checks the order of the two files an improving checkpoint writes.
"""

from __future__ import annotations

import codecs
import os
import random
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from worldmodel import artifacts, train_agent, train_vae, training
from worldmodel.config import compose

REPO = Path(__file__).resolve().parent.parent
VAE_BAR = re.compile(r"vae epoch (\d+)/\d+:\s*\d+%\|[^|]*\|\s*(\d+)/")  # -> epoch (1-based), batches done
AGENT_BAR = re.compile(r"agent r1:\s*\d+%\|[^|]*\|\s*(\d+)/")  # -> steps done
VAE_ARGS = ("vae.batch_size=4",)  # ~19 batches per epoch at scale=smoke, so a signal can land inside one
WARMUP = 100  # agent.ddpg.warmup_steps at scale=smoke: the agent's optimisers step once per environment step after it


def smoke(stage: str, data: Path, runs: Path, *overrides: str):
    return compose(
        stage,
        [f"paths.data_root={data}", f"paths.runs_root={runs}", "experiment=t", "scale=smoke", "threads=1", *overrides],
    )


@pytest.fixture(scope="module")
def rollouts(smoke_builds) -> Path:
    """``data/`` root of the session's smoke-scale experiment, built by the real stages (the tests only read it)."""
    return smoke_builds("rnn") / "data"


@pytest.fixture(scope="module")
def world_model(smoke_builds) -> Path:
    """``runs/`` root holding the session's smoke-scale VAE and LSTM (read only; the tests copy what they change)."""
    return smoke_builds("rnn") / "runs"


@pytest.fixture(scope="module")
def uninterrupted_vae(rollouts, tmp_path_factory):
    """uninterrupted_vae(epochs) -> last.pt of a VAE trained without interruption (batch size 4), once per size."""
    root, done = tmp_path_factory.mktemp("straight"), {}

    def last(epochs: int) -> dict:
        if epochs not in done:
            runs = root / f"epochs{epochs}"
            train_vae.run(smoke("train_vae", rollouts, runs, *VAE_ARGS, f"vae.epochs={epochs}"))
            done[epochs] = load(runs / "t/vae/last.pt")
        return done[epochs]

    return last


class Stage:
    """A training stage in a subprocess of its own process group, with its output readable while it runs."""

    def __init__(self, module: str, data: Path, runs: Path, *overrides: str):
        cmd = [
            sys.executable,
            "-m",
            f"worldmodel.{module}",
            f"paths.data_root={data}",
            f"paths.runs_root={runs}",
            "experiment=t",
            "scale=smoke",
            "threads=1",
            *overrides,
        ]
        self.proc = subprocess.Popen(
            cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True
        )
        self._fd = self.proc.stdout.fileno()
        os.set_blocking(self._fd, False)
        self._decode = codecs.getincrementaldecoder("utf-8")(errors="replace").decode
        self.output = ""

    def _read(self) -> None:
        while True:
            try:
                chunk = os.read(self._fd, 1 << 16)
            except BlockingIOError:
                return
            if not chunk:
                return
            self.output += self._decode(chunk)

    def progress(self, bar: re.Pattern) -> tuple[int, ...] | None:
        """The numbers of the latest redraw of a tqdm bar, or None before its first one."""
        found = bar.findall(self.output[-4000:])
        if not found:
            return None
        last = found[-1]
        return tuple(int(x) for x in (last if isinstance(last, tuple) else (last,)))

    def wait_until(self, condition, what: str, timeout: float = 300.0) -> None:
        deadline = time.monotonic() + timeout
        while True:
            self._read()
            if condition():
                return
            if self.proc.poll() is not None:
                self._read()
                raise AssertionError(
                    f"the stage ended (status {self.proc.returncode}) before {what}:\n{self.output[-3000:]}"
                )
            if time.monotonic() > deadline:
                raise AssertionError(f"no {what} within {timeout} s:\n{self.output[-3000:]}")
            time.sleep(0.02)

    def signal(self, sig: signal.Signals) -> None:
        """Like Ctrl-C in a terminal, or `kill -SIG -PGID`: to the whole process group."""
        os.killpg(self.proc.pid, sig)

    def finish(self, timeout: float = 120.0) -> int:
        self.proc.wait(timeout=timeout)
        os.set_blocking(self._fd, True)
        self._read()
        return self.proc.returncode

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self.proc.poll() is None:  # a failed assertion left it running
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        self.proc.stdout.close()
        return False


def load(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)


def adam_steps(optimizer_state: dict) -> int:
    """Optimiser steps taken, as Adam counts them (the same for every parameter)."""
    steps = {int(s["step"]) for s in optimizer_state["state"].values()}
    assert len(steps) == 1, steps
    return steps.pop()


# ----------------------------------------------------------------------------- VAE
def test_vae_sigterm_mid_epoch_then_resume_equals_uninterrupted(rollouts, uninterrupted_vae, tmp_path):
    out = tmp_path / "runs/t/vae"
    with Stage("train_vae", rollouts, tmp_path / "runs", "vae.epochs=200", *VAE_ARGS) as run:
        # into the second epoch, a few batches past the first epoch's checkpoint
        run.wait_until(lambda: (p := run.progress(VAE_BAR)) is not None and p >= (2, 3), "a few batches of epoch 2")
        run.signal(signal.SIGTERM)
        assert run.finish() == 0, run.output
    assert "SIGTERM received" in run.output and "resume with resume=true" in run.output
    state = load(out / "last.pt")
    stopped_epoch, stopped_step = state["epoch"], state["step"]
    assert f"stopped at step {stopped_step}" in run.output
    assert 1 <= stopped_epoch < 200
    assert state["batch_in_epoch"] > 0, "the stop should land inside an epoch"

    # Finish the interrupted epoch with resume=true, and compare with a run that was never interrupted.
    target = stopped_epoch + 1
    train_vae.run(smoke("train_vae", rollouts, tmp_path / "runs", *VAE_ARGS, f"vae.epochs={target}", "resume=true"))
    resumed = load(out / "last.pt")
    assert resumed["epoch"] == target and resumed["step"] > stopped_step
    ref = uninterrupted_vae(target)
    assert ref["step"] == resumed["step"]
    for k, v in ref["model"].items():
        assert torch.equal(v, resumed["model"][k]), k  # bit for bit


def test_vae_sigkill_loses_only_the_current_epoch_and_resume_equals_uninterrupted(
    rollouts, uninterrupted_vae, tmp_path
):
    out = tmp_path / "runs/t/vae"
    with Stage("train_vae", rollouts, tmp_path / "runs", "vae.epochs=200", *VAE_ARGS) as run:
        run.wait_until(
            lambda: (out / "last.pt").exists() and (p := run.progress(VAE_BAR)) is not None and p >= (2, 3),
            "a checkpoint and a few batches of the next epoch",
        )
        shown_epoch = run.progress(VAE_BAR)[0]
        run.signal(signal.SIGKILL)
        assert run.finish() == -signal.SIGKILL
    assert "stopped at step" not in run.output  # it had no chance to save

    # The VAE checkpoints at epoch ends: last.pt is a whole epoch, the one before the epoch that was killed.
    state = load(out / "last.pt")
    assert state["batch_in_epoch"] == 0 and state["epoch"] >= shown_epoch - 1 >= 1
    best = load(out / "best.pt")
    assert best["best_val"] == state["best_val"] or best["step"] > state["step"]
    target = state["epoch"] + 1
    train_vae.run(smoke("train_vae", rollouts, tmp_path / "runs", *VAE_ARGS, f"vae.epochs={target}", "resume=true"))
    resumed = load(out / "last.pt")
    assert resumed["epoch"] == target and (out / "metrics.json").exists()
    ref = uninterrupted_vae(target)
    assert ref["step"] == resumed["step"] > state["step"]
    for k, v in ref["model"].items():
        assert torch.equal(v, resumed["model"][k]), k  # bit for bit


# ----------------------------------------------------------------------------- agent
def agent_runs(world_model: Path, tmp_path: Path) -> Path:
    """A runs root of its own for one agent test, sharing the module's (read-only) VAE and LSTM."""
    runs = tmp_path / "runs"
    (runs / "t").mkdir(parents=True)
    for stage in ("vae", "rnn"):
        (runs / "t" / stage).symlink_to(world_model / "t" / stage, target_is_directory=True)
    return runs


@pytest.fixture(scope="module")
def uninterrupted_agent(rollouts, world_model, tmp_path_factory) -> dict:
    """last.pt of the smoke R1 agent trained for its 300 steps without interruption."""
    runs = agent_runs(world_model, tmp_path_factory.mktemp("straight-agent"))
    train_agent.run(smoke("train_agent", rollouts, runs, "reward=r1"))
    return load(artifacts.agent_dir(smoke("train_agent", rollouts, runs, "reward=r1")) / "last.pt")


def check_same_agent(final: dict, straight: dict) -> None:
    """Every replay row, weight and optimiser state equals the uninterrupted run's (tests/test_resume.py checks
    the rest of the checkpoint, the metrics and the curves)."""
    for name in ("obs", "actions", "rewards", "next_obs", "terminated", "steps"):
        assert np.array_equal(final["buffer"][name], straight["buffer"][name]), name
    for net in ("actor", "critic", "actor_target", "critic_target"):
        for key, value in straight["agent"][net].items():
            assert torch.equal(final["agent"][net][key], value), f"{net}.{key}"
    assert final["episode"] == straight["episode"]


def check_agent_checkpoint(state: dict, step: int) -> None:
    """A checkpoint at ``step``: one transition per step in the buffer, one optimiser step per step after warm-up."""
    assert state["step"] == step
    assert state["buffer"]["size"] == len(state["buffer"]["obs"]) == step
    for opt in ("actor_optimizer", "critic_optimizer"):
        assert adam_steps(state["agent"][opt]) == step - WARMUP, opt


def test_agent_sigterm_and_sigint_save_and_resume_finishes(rollouts, world_model, uninterrupted_agent, tmp_path):
    runs = agent_runs(world_model, tmp_path)
    out = artifacts.agent_dir(smoke("train_agent", rollouts, runs, "reward=r1"))
    # No periodic checkpoint within the run: every last.pt below was written by the stop itself.
    args = ("reward=r1", "agent.checkpoint_every=100000")
    with Stage("train_agent", rollouts, runs, *args) as run:
        run.wait_until(
            lambda: (p := run.progress(AGENT_BAR)) is not None and p[0] >= WARMUP + 20, "20 steps past the warm-up"
        )
        run.signal(signal.SIGTERM)
        assert run.finish() == 0, run.output
    first = load(out / "last.pt")
    n1 = first["step"]
    assert "SIGTERM received" in run.output and f"stopped at step {n1}; resume with resume=true" in run.output
    assert WARMUP < n1 < 300, "the stop should land after the warm-up and before the end"
    check_agent_checkpoint(first, n1)
    assert not (out / "metrics.json").exists()

    with Stage("train_agent", rollouts, runs, *args, "resume=true") as run:
        run.wait_until(
            lambda: (p := run.progress(AGENT_BAR)) is not None and p[0] >= n1 + 10, "10 steps past the resumed step"
        )
        run.signal(signal.SIGINT)  # Ctrl-C
        assert run.finish() == 0, run.output
    second = load(out / "last.pt")
    n2 = second["step"]
    assert f"resuming from {out / 'last.pt'}: step {n1}" in run.output
    assert "SIGINT received" in run.output and f"stopped at step {n2}; resume with resume=true" in run.output
    assert n1 < n2 < 300
    check_agent_checkpoint(second, n2)
    assert np.array_equal(second["buffer"]["obs"][:n1], first["buffer"]["obs"][:n1])

    metrics = train_agent.run(smoke("train_agent", rollouts, runs, *args, "resume=true"))
    assert metrics["steps"] == 300 and (out / "metrics.json").exists()
    final = load(out / "last.pt")
    check_agent_checkpoint(final, 300)
    for name in ("obs", "actions", "rewards"):
        assert np.array_equal(final["buffer"][name][:n2], second["buffer"][name][:n2]), name
    check_same_agent(final, uninterrupted_agent)  # two stops in other processes change nothing


def test_agent_sigkill_resumes_from_the_last_periodic_checkpoint(rollouts, world_model, uninterrupted_agent, tmp_path):
    runs = agent_runs(world_model, tmp_path)
    out = artifacts.agent_dir(smoke("train_agent", rollouts, runs, "reward=r1"))
    every = 50
    args = ("reward=r1", f"agent.checkpoint_every={every}")
    with Stage("train_agent", rollouts, runs, *args) as run:
        # Past the checkpoint at step 150 (after the warm-up) and on towards the next one.
        run.wait_until(
            lambda: (p := run.progress(AGENT_BAR)) is not None and p[0] >= 3 * every + 20,
            "20 steps past the third checkpoint",
        )
        run.signal(signal.SIGKILL)
        assert run.finish() == -signal.SIGKILL
        reached = run.progress(AGENT_BAR)[0]  # a lower bound: the bar redraws every 0.1 s
    assert "stopped at step" not in run.output

    state = load(out / "last.pt")  # readable: the kill never leaves a half-written checkpoint
    killed_at = state["step"]
    assert killed_at % every == 0 and 3 * every <= killed_at < 300, killed_at
    assert killed_at <= reached + every
    check_agent_checkpoint(state, killed_at)
    assert not (out / "metrics.json").exists()

    metrics = train_agent.run(smoke("train_agent", rollouts, runs, *args, "resume=true"))
    assert metrics["steps"] == 300
    final = load(out / "last.pt")
    # The steps after killed_at were lost and redone, not appended: 300 transitions and updates in all.
    check_agent_checkpoint(final, 300)
    for name in ("obs", "actions", "rewards", "next_obs", "terminated"):
        assert np.array_equal(final["buffer"][name][:killed_at], state["buffer"][name]), name
    check_same_agent(final, uninterrupted_agent)  # a periodic checkpoint, inside an episode or not, loses nothing


# ----------------------------------------------------------------------------- checkpoint files
KEEP_SAVING = """
import sys, time
from pathlib import Path
import torch
from worldmodel.config import compose
from worldmodel.training import TrainingRun
ckpts = TrainingRun(compose("train_vae"), "train_vae", Path(sys.argv[1]), record={})
i = 0
while True:
    i += 1
    state = {"step": i, "weights": torch.full((4_000_000,), float(i))}   # 16 MB, so that a save takes a while
    print(f"saving {i}", flush=True)
    t = time.perf_counter()
    ckpts.save(state, best=i % 2 == 0)
    print(f"saved {i} in {time.perf_counter() - t:.6f} s", flush=True)
"""


def test_sigkill_while_saving_leaves_readable_checkpoints(tmp_path):
    """A process that does nothing but write checkpoints, killed at a random point inside a save."""
    proc = subprocess.Popen(
        [sys.executable, "-c", KEEP_SAVING, str(tmp_path)],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    durations = []
    try:
        for line in proc.stdout:  # progress markers: each save announces itself and reports its duration
            if line.startswith("saved"):
                durations.append(float(line.split()[-2]))
            elif line.startswith("saving") and len(durations) >= 4:
                time.sleep(random.uniform(0.0, 0.9 * min(durations)))
                break
        os.killpg(proc.pid, signal.SIGKILL)
        rest, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == -signal.SIGKILL, rest
    last, best = load(tmp_path / "last.pt"), load(tmp_path / "best.pt")
    for state in (last, best):
        assert state["step"] >= 3 and bool((state["weights"] == state["step"]).all())
    assert last["step"] >= 4 and best["step"] % 2 == 0


def test_death_between_best_and_last_never_leaves_best_behind(tmp_path, monkeypatch):
    """An improving checkpoint writes two files. If the process dies after the first, last.pt (where resume
    starts) must not claim a best that best.pt does not hold: otherwise the improvement is never written."""
    ckpts = training.TrainingRun(compose("train_vae"), "train_vae", tmp_path, record={})
    ckpts.save({"step": 1, "best_val": 5.0}, best=True)

    class Killed(BaseException):
        pass

    real, writes = training.atomic_torch_save, []

    def dies_after_one_write(obj, path):
        if writes:
            raise Killed
        writes.append(path)
        real(obj, path)

    monkeypatch.setattr(training, "atomic_torch_save", dies_after_one_write)
    with pytest.raises(Killed):
        ckpts.save({"step": 2, "best_val": 3.0}, best=True)
    last, best = load(ckpts.last), load(ckpts.best)
    # Either both hold the new best, or best.pt is ahead of the resume point (which then redoes step 2).
    assert last["best_val"] == best["best_val"] or best["step"] > last["step"], (last, best)


def test_leftover_temporary_checkpoint_is_removed_on_start(tmp_path, dead_pid):
    """A kill inside a save leaves `.last.pt.tmp-PID`; the next start of that run deletes it, and only it: the
    temporary file of a writer that still runs (another process saving into the same folder) stays."""
    import subprocess
    import sys

    from worldmodel.common import atomic_torch_save, rng_state

    cfg = compose("train_vae", ["resume=true"])
    atomic_torch_save({"step": 3, "rng": rng_state()}, tmp_path / "last.pt")
    stale = tmp_path / f".last.pt.tmp-{dead_pid}"
    stale.write_bytes(b"half a checkpoint")
    keep = tmp_path / "notes.tmp"
    keep.write_text("not ours")
    writer = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    live = tmp_path / f".best.pt.tmp-{writer.pid}"
    live.write_bytes(b"being written")
    try:
        with training.TrainingRun(cfg, "train_vae", tmp_path, record={"inputs": {}, "config": "c"}) as run:
            assert run.state["step"] == 3
    finally:
        writer.kill()
        writer.wait()
    assert not stale.exists() and keep.exists() and (tmp_path / "last.pt").exists()
    assert live.exists()


# ----------------------------------------------------------------------------- the pipeline
def test_an_interrupted_pipeline_step_keeps_its_time_and_a_resume_adds_to_it(rollouts, world_model, tmp_path):
    """Ctrl-C in an agent step: pipeline.json records the time so far (not complete), plan=true shows it, and the
    rerun that finishes the step adds to it (two invocations). A step resumed after a kill -9, which recorded
    nothing, says that its time is a lower bound."""
    import json

    from worldmodel import pipeline

    runs = agent_runs(world_model, tmp_path)
    args = ("agents=[ddpg]", "evaluate.policies=[braking]")
    timings = runs / "t/pipeline.json"
    with Stage("pipeline", rollouts, runs, *args) as run:
        run.wait_until(
            lambda: (p := run.progress(AGENT_BAR)) is not None and p[0] >= WARMUP + 20, "20 steps past the warm-up"
        )
        run.signal(signal.SIGINT)
        assert run.finish() == 0, run.output
    first = json.loads(timings.read_text())["agent_r1"]
    assert "agent_r1 was interrupted" in run.output
    assert (first["complete"], first["invocations"], first["untimed_part"]) == (False, 1, False)
    assert first["wall_s"] > 0

    rows = {r["step"]: r for r in pipeline.run(smoke("pipeline", rollouts, runs, *args, "plan=true"))["plan"]}
    assert (rows["agent_r1"]["state"], rows["agent_r1"]["wall_s"]) == ("resume", first["wall_s"])
    assert rows["vae"]["state"] == rows["rnn"]["state"] == "complete" and rows["agent_r2"]["state"] == "fresh"
    assert not (runs / "t/agent_r1/seed0/metrics.json").exists()  # the plan ran nothing

    with Stage("pipeline", rollouts, runs, *args) as run:  # finishes agent_r1, then dies inside agent_r2
        run.wait_until(lambda: re.search(r"agent r2:\s*\d+%\|[^|]*\|\s*[1-9]", run.output), "agent_r2 training")
        run.signal(signal.SIGKILL)
        run.finish()
    pipeline.run(smoke("pipeline", rollouts, runs, *args))
    recorded = json.loads(timings.read_text())
    r1, r2 = recorded["agent_r1"], recorded["agent_r2"]
    assert (r1["complete"], r1["invocations"], r1["untimed_part"]) == (True, 2, False)
    assert r1["wall_s"] > first["wall_s"]
    assert (r2["complete"], r2["invocations"], r2["untimed_part"]) == (True, 1, True)
    assert recorded["eval"]["complete"] and not recorded["eval"]["untimed_part"]
