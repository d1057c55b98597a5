"""Phase 1 on real smoke-scale rollouts: resume continues exactly; errors name what to do."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from envs import CLASS_NAMES
from worldmodel import artifacts, loading, train_vae
from worldmodel.common import StageError


def scalar_steps(logdir, tag):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(logdir))
    acc.Reload()
    return [e.step for e in acc.Scalars(tag)]


@pytest.fixture
def rollouts(experiment_copy):
    return experiment_copy("rollouts")


def test_missing_dataset_names_the_collect_command(stage_cfg):
    with pytest.raises(StageError, match="worldmodel.collect experiment=t"):
        train_vae.run(stage_cfg("train_vae"))


def test_train_one_epoch_then_resume_one_more_equals_two_epochs(stage_cfg, rollouts, tmp_path, smoke_builds):
    overrides = ("vae.batch_size=8",)
    train_vae.run(stage_cfg("train_vae", *overrides, "vae.epochs=1"))
    out = tmp_path / "runs" / "t" / "vae"
    first = torch.load(out / "last.pt", weights_only=False)
    steps_one = first["step"]
    assert first["epoch"] == 1 and steps_one > 0

    with pytest.raises(StageError, match="resume=true"):
        train_vae.run(stage_cfg("train_vae", *overrides, "vae.epochs=2"))
    metrics = train_vae.run(stage_cfg("train_vae", *overrides, "vae.epochs=2", "resume=true"))
    resumed = torch.load(out / "last.pt", weights_only=False)
    assert resumed["epoch"] == 2 and resumed["step"] == 2 * steps_one
    adam_steps = {int(s["step"]) for s in resumed["optimizer"]["state"].values()}
    assert adam_steps == {2 * steps_one}
    logged = scalar_steps(out, "val/pixel_accuracy")
    assert logged == [steps_one, 2 * steps_one]

    # The same two epochs without the interruption give the same weights.
    straight = tmp_path / "straight"
    shutil.copytree(smoke_builds("rollouts"), straight)
    train_vae.run(stage_cfg("train_vae", *overrides, "vae.epochs=2", root=straight))
    ref = torch.load(straight / "runs" / "t" / "vae" / "last.pt", weights_only=False)
    for k, v in ref["model"].items():
        assert torch.equal(v, resumed["model"][k]), k  # bit for bit

    saved = json.loads((out / "metrics.json").read_text())
    assert set(saved["iou"]) == set(CLASS_NAMES) and len(CLASS_NAMES) == 13
    assert 0.0 <= saved["pixel_accuracy"] <= 1.0 and saved == metrics


def test_latent_size_mismatch_with_checkpoint_is_named(stage_cfg, rollouts):
    train_vae.run(stage_cfg("train_vae", "vae.batch_size=8"))
    with pytest.raises(StageError, match="latent"):
        train_vae.run(stage_cfg("train_vae", "vae.batch_size=8", "vae.latent_dim=64", "resume=true"))
    with pytest.raises(StageError, match="vae.latent_dim"):
        loading.load_vae(stage_cfg("train_vae", "vae.latent_dim=32"))
    # the smoke scale's 8 channels are recorded; a config of World Models' 32 is refused by name
    assert torch.load(artifacts.vae_dir(stage_cfg("train_vae")) / "last.pt", weights_only=False)["channels"] == 8
    with pytest.raises(StageError, match=r"vae.channels=8 but the config says vae.channels=32"):
        loading.load_vae(stage_cfg("train_vae", "vae.channels=32"))


@pytest.mark.parametrize(
    "override,key",
    [("vae.batch_size=0", "vae.batch_size"), ("vae.lr=-1", "vae.lr"), ("vae.free_bits=-0.5", "vae.free_bits")],
)
def test_impossible_config_stops_before_work(stage_cfg, override, key):
    with pytest.raises(StageError, match=key):
        train_vae.run(stage_cfg("train_vae", override))


def test_a_non_finite_loss_before_any_checkpoint_names_none(stage_cfg, rollouts, tmp_path):
    """The stop names a last good checkpoint only where one exists: a fresh run has none to resume from."""
    from worldmodel.common import NonFiniteLossError

    with pytest.raises(NonFiniteLossError, match="no checkpoint was saved before it") as stopped:
        train_vae.run(stage_cfg("train_vae", "vae.batch_size=8", "vae.kl_weight=1e308"))
    last = tmp_path / "runs" / "t" / "vae" / "last.pt"
    assert not last.exists() and str(last) not in str(stopped.value)


def test_non_finite_loss_stops_and_keeps_the_last_good_checkpoint(stage_cfg, rollouts, tmp_path):
    from worldmodel.common import NonFiniteLossError

    train_vae.run(stage_cfg("train_vae", "vae.batch_size=8"))
    last = tmp_path / "runs" / "t" / "vae" / "last.pt"
    good = last.read_bytes()
    # A finite KL weight so large that the loss overflows: an infinite loss on the first step after resuming (a NaN
    # weight is refused by the config check before any work)
    with pytest.raises(NonFiniteLossError, match=str(last)):
        train_vae.run(stage_cfg("train_vae", "vae.batch_size=8", "vae.epochs=2", "vae.kl_weight=1e308", "resume=true"))
    assert last.read_bytes() == good
    state = torch.load(last, weights_only=False)
    assert all(torch.isfinite(v).all() for v in state["model"].values())
