"""Restructuring the configuration keeps every artifact on disk current: the config hash each stage records in its
provenance (docs/design.md §9) is pinned here for every preset, reward, scale, family and bank. A change that moves
one of these hashes re-runs that stage (and, through its outputs, every stage after it) for every user: it must be
deliberate, and this table is updated with it."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from worldmodel import artifacts
from worldmodel.artifacts import AgentId
from worldmodel.config import agent_preset, compose, preset_globals

PRESETS = (
    "ddpg",
    "dag",
    "chooser",
    "chooser_tele",
    "dqn_chae",
    "ddpg_kim",
    "ddpg_kim_fd",
    "ddqn_merola",
    "ddpg_wm_kim",
    "kim_chooser",
)
PINNED = {
    "quick/vae": "3d10eeb7fb9e341a",
    "quick/rnn": "09469dc1cd955a81",
    "quick/ddpg/r1": "b2a1bd3578a58f5d",
    "quick/ddpg/r2": "3c24f0587f746603",
    "quick/dag/r2": "29ef90e613014516",
    "quick/chooser/r2": "511327ee17f9ddea",
    "quick/chooser_tele/r2": "ad72ef88653384e6",
    "quick/dqn_chae/chae": "dce6794e6773e2f4",
    "quick/ddpg_kim/kim_unaware": "c470a8f2b114c697",
    "quick/ddpg_kim/kim_aware": "3b950952a185da5b",
    "quick/ddpg_kim_fd/kim_unaware": "880e1c5cc55fa065",
    "quick/ddqn_merola/merola": "5932fd469b5cfc70",
    "quick/ddpg_wm_kim/kim_unaware": "93495741c874f052",
    "quick/kim_chooser/kim_unaware": "e9d3a5ec385af551",
    "quick/eval/porav/validation": "824450fb4750e975",
    "quick/eval/porav/test": "065f42ca3ab337bd",
    "quick/eval/chae/validation": "d4511a14cff48918",
    "quick/eval/chae/test": "4cd241ae967337ec",
    "quick/eval/kim/validation": "ffbf37a965ef6185",
    "quick/eval/kim/test": "61eda4b850a5d1e1",
    "quick/eval/merola/validation": "6c7ef3aa0c132d90",
    "quick/eval/merola/test": "9cc1ac5a9eb886bf",
    "paper/vae": "c6492a5d65899f1a",
    "paper/rnn": "76bce04c590fe807",
    "paper/ddpg/r1": "e0b898181c30312e",
    "paper/ddpg/r2": "94bf4439332b6c31",
    "paper/dag/r2": "1043009feccf3a0c",
    "paper/chooser/r2": "def78904480db9b8",
    "paper/chooser_tele/r2": "57b071b15c7c1b86",
    "paper/dqn_chae/chae": "77b63804959de1cd",
    "paper/ddpg_kim/kim_unaware": "cefd165ddd340db8",
    "paper/ddpg_kim/kim_aware": "5dffe55bf368d743",
    "paper/ddpg_kim_fd/kim_unaware": "46de41f5e2f6c6d3",
    "paper/ddqn_merola/merola": "cdd7513661851a4c",
    "paper/ddpg_wm_kim/kim_unaware": "761705858e99be2b",
    "paper/kim_chooser/kim_unaware": "012d188975dcdfd0",
    "paper/eval/porav/validation": "66629d99bb06c2ae",
    "paper/eval/porav/test": "ff9bf81bd778998d",
    "paper/eval/chae/validation": "77ebe01e9088736f",
    "paper/eval/chae/test": "7d9a57727bebee86",
    "paper/eval/kim/validation": "319cab3fe5071765",
    "paper/eval/kim/test": "6fdf0027606955c5",
    "paper/eval/merola/validation": "752cb905eda0530e",
    "paper/eval/merola/test": "d1b25d24d81d78ed",
}


def current_hashes(scale: str) -> dict[str, str]:
    base = compose(
        "pipeline",
        [f"scale={scale}", "paths.runs_root=/nonexistent", "paths.data_root=/nonexistent", "demos.episodes=500"],
    )
    out = {f"{scale}/{stage}": artifacts.provenance(base, stage)["config"][:16] for stage in ("vae", "rnn")}
    for preset in PRESETS:
        agent = agent_preset(base, preset)
        for reward in agent.rewards:
            cfg = OmegaConf.merge(base, preset_globals(preset), {"agent": agent, "reward": {"name": reward}})
            key = f"{scale}/{preset}/{reward}"
            out[key] = artifacts.provenance(cfg, "agent", AgentId(reward, 0, preset))["config"][:16]
    for family in ("porav", "chae", "kim", "merola"):
        for bank in ("validation", "test"):
            cfg = OmegaConf.merge(base, {"evaluate": {"family": family, "bank": bank}})
            out[f"{scale}/eval/{family}/{bank}"] = artifacts.provenance(cfg, "eval")["config"][:16]
    return out


@pytest.mark.parametrize("scale", ["quick", "paper"])
def test_every_recorded_config_hash_is_unchanged(scale):
    now = current_hashes(scale)
    pinned = {k: v for k, v in PINNED.items() if k.startswith(f"{scale}/")}
    changed = sorted(k for k in pinned if now.get(k) != pinned[k])
    assert not changed, f"these stages would re-run for every user: {changed}"
    assert set(now) == set(pinned)


@pytest.mark.parametrize(
    "changes",
    [
        ["paths.data_root=/tmp/a/data", "paths.runs_root=/tmp/a/runs", "paths.ledger=/tmp/a/ledger.csv"],
        ["paths.data_root=/tmp/b/data", "paths.runs_root=relative/runs", "seed=3", "agent.total_steps=70"],
        ["paths.data_root=/tmp/c", "paths.data_root=/tmp/d"],  # given twice: the last, as Hydra says
        ["paths.runs_root=${paths.data_root}/runs"],  # an interpolation stays one
        ["paths.ledger='/tmp/e/ledger.csv'", "banks=[validation,test]"],  # Hydra's grammar: quotes off, a list
        ["agent.chooser.steers=[1.0]", "agent.chooser.decide_s=0.5", "launcher=local"],  # a key, not hydra/launcher
        ["reward=r1", "view=cover64", "obs=privileged"],  # choices of config groups, after the preset's own
        ["+agent.not_a_key=1"],  # an addition: Hydra's composition refuses it, as it would
        ["agent.not_a_key=1"],  # no such key: Hydra's own error
        ["~agent.chooser"],  # a deletion
        ["agent.total_steps=1,2"],  # a sweep, which a composition refuses
        ["agent.total_steps=[oops"],  # text Hydra's parser refuses
    ],
)
def test_compose_gives_what_hydra_composes_and_a_config_of_its_own(changes):
    """``compose`` composes once per stage and choice of config groups, then applies the other overrides to a copy
    with Hydra's own code: the config is Hydra's own, key for key and node type for node type (or Hydra's own
    error), and changing it changes no later one."""
    from worldmodel.config.entry import _hydra_compose

    def composed(how):
        try:
            return how("train_agent", [*changes, "experiment=t", "scale=smoke", "agent=chooser", "reward=r2"])
        except Exception as err:  # noqa: BLE001 - the same error is the check
            return f"{type(err).__name__}: {err}"

    for _ in range(2):  # composed, then from what compose keeps
        cfg, hydra = composed(compose), composed(_hydra_compose)
        if isinstance(hydra, str):
            assert cfg == hydra
            continue
        assert OmegaConf.to_yaml(cfg) == OmegaConf.to_yaml(hydra)
        assert OmegaConf.to_container(cfg, resolve=True) == OmegaConf.to_container(hydra, resolve=True)
        assert OmegaConf.get_type(cfg.agent) is OmegaConf.get_type(hydra.agent) and OmegaConf.is_struct(cfg)
        cfg.agent.total_steps = 7
    assert isinstance(hydra, str) or composed(compose).agent.total_steps != 7


def test_compose_sees_a_preset_registered_after_it_composed_and_its_removal():
    """What compose keeps is keyed by what a composition reads besides its arguments, Hydra's ConfigStore among it."""
    from hydra.core.config_store import ConfigStore
    from hydra.errors import ConfigCompositionException

    overrides = ["experiment=t", "scale=smoke"]
    before = compose("train_agent", overrides)
    preset = {"agent": {"variant": "registered_here", "total_steps": 11}}
    ConfigStore.instance().store(group="agent", name="registered_here", node=preset, package="_global_")
    try:
        assert compose("train_agent", [*overrides, "agent=registered_here"]).agent.total_steps == 11
    finally:
        ConfigStore.instance().repo["agent"].pop("registered_here.yaml")
    with pytest.raises(ConfigCompositionException):
        compose("train_agent", [*overrides, "agent=registered_here"])
    assert OmegaConf.to_yaml(compose("train_agent", overrides)) == OmegaConf.to_yaml(before)
