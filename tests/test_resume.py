"""Every learner, stopped and resumed, ends bit for bit where an uninterrupted run of the same config ends.

A run is stopped the way a cluster's time limit stops it: a real SIGTERM, delivered to this process from a
torch optimiser step hook (``torch.optim.optimizer.register_optimizer_step_pre_hook``) at a chosen update, so
it lands in the middle of an episode, while the learner is busy. The stage's own signal handler turns it into a
checkpoint and a clean return; ``resume=true`` then finishes the run. The DDPG agent is also stopped by a shorter
``agent.total_steps``, which ends it mid-episode at an exact step.

"The same result" is everything the run leaves: every tensor, array and counter of ``last.pt`` (weights,
optimiser state, replay buffer and trauma memory, random generators, episode count), ``metrics.json`` but for
its wall-clock speed, and every TensorBoard scalar with its step but for the ``speed/`` curves.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.optim.optimizer import register_optimizer_step_pre_hook

from worldmodel import artifacts, train_agent, train_rnn

# metrics.json keys that describe one invocation, not the run: the machine's speed (``*wall_s``, ``*per_s``), and
# whether this invocation (re)encoded the latents or found them encoded
INVOCATION = ("reencoded_latents",)


def invocation_key(key: str) -> bool:
    return key in INVOCATION or key.endswith(("wall_s", "per_s", "seconds"))


@contextlib.contextmanager
def sigterm_at_update(n: int):
    """Send this process SIGTERM just before the ``n``-th optimiser step of any torch optimiser (1-based)."""
    count = 0

    def hook(optimizer, args, kwargs):
        nonlocal count
        count += 1
        if count == n:
            os.kill(os.getpid(), signal.SIGTERM)

    handle = register_optimizer_step_pre_hook(hook)
    try:
        yield
    finally:
        handle.remove()
    assert count >= n, f"the run made {count} optimiser steps, fewer than the {n} the stop was planned at"


def assert_same(a, b, where: str = "") -> None:
    """Bit-for-bit equality of two checkpoints (nested dicts, lists, tensors, arrays, numbers)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), f"{where}: keys {sorted(a)} != {sorted(b)}"
        for k in a:
            assert_same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert isinstance(b, (list, tuple)) and len(a) == len(b), f"{where}: lengths differ"
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, torch.Tensor):
        assert torch.equal(a, b), f"{where}: tensors differ (max {float((a.double() - b.double()).abs().max())})"
    elif isinstance(a, np.ndarray):
        assert np.array_equal(a, b), f"{where}: arrays differ"
    elif isinstance(a, float) and np.isnan(a):
        assert isinstance(b, float) and np.isnan(b), where
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


def scalars(run_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """Every TensorBoard scalar of a run and of its side folders (pre-training), as a reader sees it: events a
    resumed run purged are gone."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out = {}
    for folder in sorted({p.parent for p in run_dir.rglob("events.out.tfevents.*")}):
        acc = EventAccumulator(str(folder), size_guidance={"scalars": 0})
        acc.Reload()
        for tag in acc.Tags()["scalars"]:
            if not tag.startswith("speed/"):
                out[f"{folder.relative_to(run_dir)}:{tag}"] = [(e.step, e.value) for e in acc.Scalars(tag)]
    return out


def metrics(run_dir: Path) -> dict:
    root = Path(*run_dir.parts[: run_dir.parts.index("runs")])  # the copy's own folder, which paths name
    out = json.loads((run_dir / "metrics.json").read_text().replace(str(root), "<root>"))
    return {k: v for k, v in out.items() if not invocation_key(k)}


def assert_same_run(straight: Path, resumed: Path) -> None:
    assert_same(
        torch.load(straight / "last.pt", weights_only=False), torch.load(resumed / "last.pt", weights_only=False)
    )
    assert metrics(straight) == metrics(resumed)
    a, b = scalars(straight), scalars(resumed)
    assert a.keys() == b.keys()
    for tag in a:
        assert a[tag] == b[tag], f"TensorBoard {tag} differs"


def stopped_then_resumed(stage_cfg, root: Path, run, stage: str, overrides: tuple, stop_at_update: int) -> dict:
    """Run a stage that SIGTERM stops at an update, check that it stopped, and return what the stage returned."""
    with sigterm_at_update(stop_at_update):
        out = run(stage_cfg(stage, *overrides, root=root))
    assert out.get("stopped"), "the SIGTERM should have stopped the run before its end"
    return out


def agent_resumes_bit_for_bit(stage_cfg, straight: Path, stopped: Path, overrides: tuple, stop_at_update: int):
    """train_agent uninterrupted under ``straight``; stopped at an update, then resumed, under ``stopped``; the same."""
    train_agent.run(stage_cfg("train_agent", *overrides, root=straight))
    stopped_then_resumed(stage_cfg, stopped, train_agent.run, "train_agent", overrides, stop_at_update)
    train_agent.run(stage_cfg("train_agent", *overrides, "resume=true", root=stopped))
    assert_same_run(
        artifacts.agent_dir(stage_cfg("train_agent", *overrides, root=straight)),
        artifacts.agent_dir(stage_cfg("train_agent", *overrides, root=stopped)),
    )


@pytest.fixture
def two_roots(experiment_copy, tmp_path):
    """Two private copies of the smoke world model: one for the uninterrupted run, one for the interrupted one."""

    def make(level: str = "rnn") -> tuple[Path, Path]:
        straight = experiment_copy(level)
        other = tmp_path.parent / f"{tmp_path.name}-resumed"
        shutil.copytree(straight, other)
        return straight, other

    return make


# ----------------------------------------------------------------------------- the paper's DDPG agent
def test_ddpg_stopped_by_a_shorter_total_resumes_bit_for_bit(two_roots, stage_cfg):
    """The example a user hits first: stop at 150 steps (mid-episode), resume to 300."""
    a, b = two_roots()
    train_agent.run(stage_cfg("train_agent", "reward=r1", root=a))
    train_agent.run(stage_cfg("train_agent", "reward=r1", "agent.total_steps=150", root=b))
    state = torch.load(
        artifacts.agent_dir(stage_cfg("train_agent", "reward=r1", root=b)) / "last.pt", weights_only=False
    )
    assert state["step"] == 150 and len(state["in_progress"]["actions"]) > 0, "the stop should land mid-episode"
    train_agent.run(stage_cfg("train_agent", "reward=r1", "resume=true", root=b))
    cfg = stage_cfg("train_agent", "reward=r1", root=a)
    assert_same_run(artifacts.agent_dir(cfg), artifacts.agent_dir(stage_cfg("train_agent", "reward=r1", root=b)))


def test_privileged_ddpg_stopped_by_a_shorter_total_resumes_bit_for_bit(stage_cfg, tmp_path):
    """obs=privileged (the true state, no world model): the replayed episode rebuilds its observation too."""
    a, b = tmp_path / "straight", tmp_path / "stopped"
    agent = ("agent=ddpg", "obs=privileged", "reward=r2")
    train_agent.run(stage_cfg("train_agent", *agent, root=a))
    train_agent.run(stage_cfg("train_agent", *agent, "agent.total_steps=150", root=b))
    state = torch.load(artifacts.agent_dir(stage_cfg("train_agent", *agent, root=b)) / "last.pt", weights_only=False)
    assert state["step"] == 150 and len(state["in_progress"]["actions"]) > 0, "the stop should land mid-episode"
    train_agent.run(stage_cfg("train_agent", *agent, "resume=true", root=b))
    assert_same_run(
        artifacts.agent_dir(stage_cfg("train_agent", *agent, root=a)),
        artifacts.agent_dir(stage_cfg("train_agent", *agent, root=b)),
    )


def test_ddpg_variant_sigterm_mid_episode_resumes_bit_for_bit(two_roots, stage_cfg):
    """TD3's options and 3-step returns: the stop leaves transitions waiting in the n-step window."""
    a, b = two_roots()
    variant = (
        "reward=r2",
        "agent.ddpg.twin_critics=true",
        "agent.ddpg.policy_delay=2",
        "agent.ddpg.target_noise=0.2",
        "agent.ddpg.n_step=3",
    )
    train_agent.run(stage_cfg("train_agent", *variant, root=a))
    # the warm-up ends at step 100; each step after it makes two optimiser steps (actor and critic) or one
    stopped_then_resumed(stage_cfg, b, train_agent.run, "train_agent", variant, stop_at_update=61)
    state = torch.load(artifacts.agent_dir(stage_cfg("train_agent", *variant, root=b)) / "last.pt", weights_only=False)
    assert 100 < state["step"] < 300
    assert len(state["in_progress"]["actions"]) > 0 and len(state["in_progress"]["window"]) > 0
    train_agent.run(stage_cfg("train_agent", *variant, "resume=true", root=b))
    assert_same_run(
        artifacts.agent_dir(stage_cfg("train_agent", *variant, root=a)),
        artifacts.agent_dir(stage_cfg("train_agent", *variant, root=b)),
    )


# ----------------------------------------------------------------------------- the world model's LSTM
def test_lstm_sigterm_mid_epoch_resumes_bit_for_bit(two_roots, stage_cfg):
    a, b = two_roots("vae")
    epochs = ("rnn.epochs=2", "rnn.effect_points=0", "rnn.horizon_episodes=0")  # the training alone, not the dreams
    train_rnn.run(stage_cfg("train_rnn", *epochs, root=a))
    stopped_then_resumed(stage_cfg, b, train_rnn.run, "train_rnn", epochs, stop_at_update=3)
    train_rnn.run(stage_cfg("train_rnn", *epochs, "resume=true", root=b))
    assert_same_run(
        artifacts.runs_root(stage_cfg("train_rnn", root=a)) / "rnn",
        artifacts.runs_root(stage_cfg("train_rnn", root=b)) / "rnn",
    )


# ----------------------------------------------------------------------------- cloning and DAgger
def test_cloning_and_dagger_sigterm_mid_round_resume_bit_for_bit(two_roots, stage_cfg):
    """The planner cloned, one DAgger round, then DDPG from demonstrations: a stop inside the first cloning round
    waits for the round's end, which is saved; the resumed run labels, clones and trains on exactly as before."""
    from worldmodel import demonstrate

    a, b = two_roots()
    demos = ("demos.episodes=3", "demos.episodes_per_shard=1", "demos.num_workers=1")
    student = (
        *("agent.anchor=brake", "agent.steer=grip", "agent.use_speed=true", "agent.ddpg.actor_final_bound=0"),
        *("agent.bc_pretrain_steps=30", "agent.dagger_rounds=1", "agent.dagger_episodes=1"),
        *("agent.demo_share=0.25", "agent.total_steps=150", "reward=r2", *demos),
    )
    demonstrate.run(stage_cfg("demonstrate", *demos, root=a))
    shutil.copytree(a / "data/t/demos", b / "data/t/demos")
    train_agent.run(stage_cfg("train_agent", *student, root=a))
    stopped_then_resumed(stage_cfg, b, train_agent.run, "train_agent", student, stop_at_update=10)
    state = torch.load(artifacts.agent_dir(stage_cfg("train_agent", *student, root=b)) / "last.pt", weights_only=False)
    assert state["cloned_rounds"] == 1 and state["step"] == 0 and state["cloning_set"] is not None
    train_agent.run(stage_cfg("train_agent", *student, "resume=true", root=b))
    assert_same_run(
        artifacts.agent_dir(stage_cfg("train_agent", *student, root=a)),
        artifacts.agent_dir(stage_cfg("train_agent", *student, root=b)),
    )


# ----------------------------------------------------------------------------- the chooser's scorer
def test_chooser_sigterm_mid_fit_resumes_bit_for_bit(two_roots, stage_cfg):
    """The scorer's fit stopped halfway: the resumed run refits it from the kept labels to the same weights."""
    a, b = two_roots()
    chooser = (
        *("reward=r2", "agent=chooser", "agent.chooser.episodes=4", "agent.chooser.steers=[1.0]"),
        *("agent.chooser.lane_change_s=[0.3]", "agent.chooser.decide_s=0.5", "agent.chooser.steps=100"),
        *("agent.chooser.batch_size=16", "agent.chooser.num_workers=1"),
    )
    agent_resumes_bit_for_bit(stage_cfg, a, b, chooser, stop_at_update=40)


# ----------------------------------------------------------------------------- the counterfactual actor
def test_counterfactual_sigterm_in_a_dagger_round_resumes_bit_for_bit(two_roots, stage_cfg):
    """Stopped while fitting the second round's critic, after the first actor has driven and its states are
    labelled: the resumed run reads both rounds' labels back and refits that critic to the same weights."""
    a, b = two_roots()
    # the smoke scale's 60 critic and 40 actor minibatches a round: update 130 is round 1's critic
    agent_resumes_bit_for_bit(stage_cfg, a, b, ("reward=r2", "agent=counterfactual"), stop_at_update=130)


def test_kim_counterfactual_sigterm_in_a_dagger_round_resumes_bit_for_bit(stage_cfg, tmp_path):
    """The same rounds on family kim's LIDAR view (agent=counterfactual_kim), no world model: stopped in round 1's
    critic, after the first actor has driven and its states are labelled."""
    a, b = tmp_path / "straight", tmp_path / "stopped"
    smoke = ("agent.counterfactual.episodes=4", "agent.counterfactual.dagger_episodes=2")
    smoke += ("agent.counterfactual.critic_steps=60", "agent.counterfactual.actor_steps=40")
    agent_resumes_bit_for_bit(stage_cfg, a, b, ("agent=counterfactual_kim", *smoke), stop_at_update=130)


def test_merola_counterfactual_sigterm_in_a_dagger_round_resumes_bit_for_bit(two_roots, stage_cfg):
    """The same rounds on family merola's nine actions (agent=counterfactual_merola), on the smoke VAE's view of the
    camera's frames: stopped in round 1's critic (no actor: 60 critic minibatches a round), after the first
    critic's choices have driven and their states are labelled."""
    a, b = two_roots("vae")
    smoke = ("agent.counterfactual.episodes=4", "agent.counterfactual.dagger_episodes=2")
    smoke += ("agent.counterfactual.critic_steps=60", "agent.counterfactual.decisions=2")
    smoke += ("agent.counterfactual.dagger_rounds=1",)  # the preset's one decision has no DAgger round
    agent_resumes_bit_for_bit(stage_cfg, a, b, ("agent=counterfactual_merola", *smoke), stop_at_update=90)


# ----------------------------------------------------------------------------- the peers' learners
# Each peer's loop checks for a stop between episodes, so a SIGTERM mid-episode ends the episode first; the
# checkpoint then holds whole episodes, and the resumed run starts the next one where the uninterrupted run does.
PEERS = {
    # Chae's braking DQN with its trauma memory, validations and rescoring, learning from step 40
    "chae": ("agent=dqn_chae", "agent.dqn.warmup_steps=40"),
    # Merola's Double DQN on the VAE's view of two frames, learning from step 40
    "merola": ("agent=ddqn_merola", "agent.dqn.warmup_steps=40"),
    # Kim's LIDAR DDPG with 3-step returns
    "kim": ("agent=ddpg_kim",),
    # and after cloning the planner with a DAgger round, demonstrations in its batches: stopped while cloning
    "kim_fd": (
        *("agent=ddpg_kim_fd", "demos.episodes=4", "agent.bc_pretrain_steps=60", "agent.dagger_rounds=1"),
        "agent.dagger_episodes=1",
    ),
}


@pytest.mark.parametrize("peer", sorted(PEERS))
def test_peer_sigterm_mid_episode_resumes_bit_for_bit(peer, two_roots, stage_cfg):
    a, b = two_roots("vae")
    agent_resumes_bit_for_bit(stage_cfg, a, b, PEERS[peer], stop_at_update=30)
