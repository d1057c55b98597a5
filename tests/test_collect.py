"""Phase 0 through the real pybullet scene and real HDF5 files."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from worldmodel import artifacts, collect
from worldmodel.common import StageError
from worldmodel.data import EPISODE_KEYS, CorruptDataError, RolloutStore, validate

REPO = Path(__file__).resolve().parent.parent


def dataset_content(root: Path) -> dict:
    """Everything a reader can see in a rollout directory, for equality checks."""
    out = {"split": (root / "split.json").read_text()}
    for path in sorted(root.glob("shard_*.h5")):
        with h5py.File(path, "r") as f:
            for key, g in f.items():
                out[(path.name, key)] = (
                    {k: g[k][...].tobytes() for k in EPISODE_KEYS},
                    {k: str(v) for k, v in g.attrs.items()},
                )
    return out


def test_smoke_collection_schema_and_reproducible(stage_cfg, tmp_path):
    cfg = stage_cfg("collect")
    summary = collect.run(cfg)
    root = artifacts.rollouts_dir(cfg)
    assert summary["episodes"] == cfg.collect.episodes == 4
    store = RolloutStore(root)
    split = store.split
    assert sorted(split["train"] + split["validation"]) == [0, 1, 2, 3] and split["validation"]
    # branched continuations (collect.branch): ids after the recorded ones, in their parent's split, starting
    # with the parent's own frames up to the branch point and then going their own way
    b = cfg.collect.branch
    assert store.branch_of and sorted(store.location) == [0, 1, 2, 3, *sorted(store.branch_of)]
    assert summary["branched_episodes"] == len(store.branch_of)
    for i, parent in store.branch_of.items():
        assert i == 4 + parent * b.actions + (i - 4) % b.actions
        attrs = store.attrs(i)
        assert attrs["branch_of"] == parent and 1 <= attrs["branch_step"] <= b.latest_step
        step, context = int(attrs["branch_step"]), min(int(attrs["branch_step"]), b.context)
        own, theirs = store.read(i, "seg"), store.read(parent, "seg")
        assert np.array_equal(own[: context + 1], theirs[step - context : step + 1])
        assert np.array_equal(store.read(i, "action")[:context], store.read(parent, "action")[step - context : step])
        held = store.read(i, "action")[context:-1]
        assert len(held) >= 1 and np.all(held == held[0])
        assert (i in store.episodes("train")) == (parent in split["train"])
        assert i not in store.episodes("train", branches=False) + store.episodes("validation", branches=False)
    for i in range(4):
        seg = store.read(i, "seg")
        n = len(seg)
        assert seg.dtype == np.uint8 and seg.shape[1:] == (64, 64) and seg.max() <= 12
        assert store.read(i, "action").shape == (n, 2) and store.read(i, "speed").shape == (n,)
        assert store.read(i, "done")[-2] == 1 and store.read(i, "done")[:-2].sum() == 0
        assert np.all(store.read(i, "action")[-1] == 0)
        attrs = store.attrs(i)
        assert attrs["n_steps"] == n - 1
        assert json.loads(attrs["scenario"])["seed"] == attrs["seed"]
        assert n <= cfg.collect.max_episode_s * 15 + 1
    with h5py.File(root / "shard_00000.h5", "r") as f:
        assert f.attrs["schema_version"] == 2

    again = stage_cfg("collect", root=tmp_path / "second")
    collect.run(again)
    assert dataset_content(root) == dataset_content(artifacts.rollouts_dir(again))
    # one identity for the same data, whatever the collection's timings
    assert artifacts.rollouts_id(again) == artifacts.rollouts_id(cfg)
    # Worker count does not change the data.
    two = stage_cfg("collect", "collect.num_workers=2", root=tmp_path / "third")
    collect.run(two)
    assert dataset_content(root) == dataset_content(artifacts.rollouts_dir(two))


def test_sigkill_then_resume_gives_exactly_the_uninterrupted_data(tmp_path, stage_cfg):
    overrides = ["collect.episodes=6", "collect.episodes_per_shard=1", "collect.num_workers=1"]
    root = tmp_path / "killed"
    cmd = [
        sys.executable,
        "-m",
        "worldmodel.collect",
        f"paths.data_root={root}/data",
        f"paths.runs_root={root}/runs",
        "experiment=t",
        "scale=smoke",
        *overrides,
    ]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    rollouts = root / "data" / "t" / "rollouts"
    deadline = time.time() + 120
    while len(list(rollouts.glob("shard_*.h5"))) < 2 and time.time() < deadline:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    written = len(list(rollouts.glob("shard_*.h5")))
    assert 2 <= written < 6 and not (rollouts / "manifest.json").exists(), "kill did not land mid-way"

    cfg = stage_cfg("collect", *overrides, root=root)
    with pytest.raises(StageError, match="resume=true"):
        collect.run(cfg)
    collect.run(stage_cfg("collect", *overrides, "resume=true", root=root))
    assert not list(rollouts.glob(".shard_*"))
    reference = stage_cfg("collect", *overrides, root=tmp_path / "clean")
    collect.run(reference)
    assert dataset_content(rollouts) == dataset_content(artifacts.rollouts_dir(reference))
    store = RolloutStore(rollouts)
    assert sorted(set(store.location) - set(store.branch_of)) == list(range(6))


def test_truncated_shard_is_named_in_the_error(stage_cfg, experiment_copy):
    experiment_copy("rollouts")
    cfg = stage_cfg("collect")
    root = artifacts.rollouts_dir(cfg)
    bad = root / "shard_00001.h5"
    size = bad.stat().st_size
    with open(bad, "r+b") as fh:
        fh.truncate(size // 2)
    with pytest.raises(CorruptDataError, match="shard_00001.h5"):
        validate(root)
    with pytest.raises(CorruptDataError, match="shard_00001.h5"):
        RolloutStore(root)
    result = subprocess.run(
        [sys.executable, "-m", "worldmodel.data", "validate", str(root)], capture_output=True, text=True, cwd=REPO
    )
    assert result.returncode == 1 and "shard_00001.h5" in result.stderr

    # the advice works: a collection resumed on the complete dataset records the damaged shard again, keeps the
    # damaged file, and the dataset is the one every stage was built on
    identity = artifacts.rollouts_id(cfg)
    with pytest.raises(StageError, match="shard_00001.h5 are missing, truncated or changed"):
        collect.run(cfg)
    collect.run(stage_cfg("collect", "resume=true"))
    validate(root)
    assert artifacts.rollouts_id(cfg) == identity
    assert [p.stat().st_size for p in (root / "damaged").iterdir()] == [size // 2]
    bad.unlink()  # a lost shard, too
    collect.run(stage_cfg("collect", "resume=true"))
    assert artifacts.rollouts_id(cfg) == identity and RolloutStore(root)


def test_changed_settings_refuse_to_mix_with_existing_data(stage_cfg, experiment_copy):
    experiment_copy("rollouts")
    with pytest.raises(StageError, match="different settings"):
        collect.run(stage_cfg("collect", "collect.episodes=5", "resume=true"))


def test_impossible_config_is_rejected_before_work(stage_cfg):
    with pytest.raises(StageError, match="collect.episodes"):
        collect.run(stage_cfg("collect", "collect.episodes=0"))


@pytest.mark.parametrize(
    "override, named",
    [
        ("seed=-1", "seed=-1"),
        ("seeds=[0,-2]", "seeds=[0, -2]"),
        ("vae.kl_weight=nan", "vae.kl_weight=nan"),
        ("vae.free_bits=nan", "vae.free_bits=nan"),
        ("agent.ddpg.exploration_noise=nan", "agent.ddpg.exploration_noise=nan"),
        ("agent.ddpg.target_noise=nan", "agent.ddpg.target_noise=nan"),
        ("agent.ddpg.bc_weight=nan", "agent.ddpg.bc_weight=nan"),
        ("vae.lr=inf", "vae.lr=inf"),
        ("agent.counterfactual.pessimism=nan", "agent.counterfactual.pessimism=nan"),
        ("experiment=''", "experiment=''"),
        ("experiment=..", "experiment='..'"),
        ("peers=[chea]", "name a peer system (chae, kim, merola)"),
        ("collect.episodes=1000000000", "collect.episodes=1000000000 needs at least 10,000 GB"),
    ],
)
def test_values_that_would_fail_later_are_refused_by_name_before_anything_is_written(
    stage_cfg, tmp_path, override, named
):
    """NaN passes every range check, a negative seed fails inside numpy, an empty experiment writes into runs/ itself
    and a misspelt peer looked like a missing preset: each is refused first, naming the key, and writes nothing."""
    with pytest.raises(StageError, match=re.escape(named)):
        collect.run(stage_cfg("collect", override))
    assert not (tmp_path / "data").exists() and not (tmp_path / "runs").exists()


def test_a_config_validated_again_comes_back_as_its_own_copy_and_a_refused_one_is_refused_again(stage_cfg):
    """validate keeps what it checked: the same config gives an equal typed config that the caller may change
    without changing the next one, and an impossible value is refused however often it is asked about."""
    from omegaconf import OmegaConf

    from worldmodel.config import validate

    cfg = stage_cfg("train_agent")
    first = validate(cfg)
    first.agent.ddpg.tau = 0.5
    again = validate(cfg)
    assert again.agent.ddpg.tau != 0.5 and again == validate(cfg) and again is not validate(cfg)
    assert validate(OmegaConf.merge(cfg, {"agent": {"ddpg": {"tau": 0.25}}})).agent.ddpg.tau == 0.25
    for _ in range(2):
        with pytest.raises(StageError, match="agent.ddpg.tau=5.0"):
            validate(OmegaConf.merge(cfg, {"agent": {"ddpg": {"tau": 5.0}}}))


def test_a_branch_under_the_parents_own_action_replays_the_parent(stage_cfg):
    """The snapshot a branch starts from is the recorded state itself: continuing it with the action the autopilot
    took reproduces the recorded next frame bit for bit."""
    from omegaconf import OmegaConf

    from worldmodel.collect import _collection_settings, autopilot_of, spec_of
    from worldmodel.recording import _worker_env, branch_episodes, record_episode

    settings = _collection_settings(stage_cfg("collect", "collect.max_episode_s=2.0"))
    env = _worker_env(settings)
    spec = spec_of(settings, 2)
    parent = record_episode(env, autopilot_of(settings, spec), spec, 2, snapshot_at=3)
    assert parent["_snapshot"] is not None and OmegaConf.create(settings["branch"]).context == 3
    (branch,) = branch_episodes(env, parent, 3, parent["action"][3:4], settings)
    assert np.array_equal(branch["seg"][:5], parent["seg"][:5])
    assert branch["branch_of"] == 2 and branch["index"] == 4 + 2 * settings["branch"]["actions"]


def test_old_and_unknown_schema_versions(stage_cfg, experiment_copy):
    """A schema-1 store (before branches) still reads, as one without branches; collecting into it is refused with
    the reason; an unknown version is named with what to do."""
    experiment_copy("rollouts")
    cfg = stage_cfg("collect")
    root = artifacts.rollouts_dir(cfg)
    config = json.loads((root / "collect_config.json").read_text())
    (root / "collect_config.json").write_text(json.dumps({**config, "schema_version": 1}))
    with pytest.raises(StageError, match="schema version 1"):
        collect.run(stage_cfg("collect", "resume=true"))
    manifest = json.loads((root / "manifest.json").read_text())
    manifest.pop("branches")
    (root / "manifest.json").write_text(json.dumps(manifest))
    for path in root.glob("shard_*.h5"):
        with h5py.File(path, "r+") as f:
            f.attrs["schema_version"] = 1
            keep = [i for i in f.attrs["episodes"] if i < 4]
            for key in [k for k in f if int(k.split("_")[1]) >= 4]:
                del f[key]
            f.attrs["episodes"] = np.array(keep, np.int64)
    store = RolloutStore(root)
    assert store.branch_of == {} and sorted(store.location) == [0, 1, 2, 3]
    with h5py.File(root / "shard_00000.h5", "r+") as f:
        f.attrs["schema_version"] = 99
    with pytest.raises(CorruptDataError, match="schema_version 99.*worldmodel.collect"):
        RolloutStore(root)
