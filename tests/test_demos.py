"""Planner demonstrations (``worldmodel.demonstrate``) and what the agent learns from them: the store is
reproducible and in the rollout schema, cloning moves the actor onto the planner's actions, and agent variants
are named and trained apart. Real planner, real camera, real HDF5 and the real smoke-scale world model."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from worldmodel import artifacts, demonstrate, imitation, loading, train_agent
from worldmodel.action_map import ActionMap
from worldmodel.common import StageError
from worldmodel.data import RolloutStore, validate
from worldmodel.learners import ddpg as ddpg_learner

DEMOS = ["demos.episodes=3", "demos.episodes_per_shard=1"]
LEARNER = [
    "agent.anchor=brake",
    "agent.steer=grip",
    "agent.use_speed=true",
    "agent.frame_view=true",
    "agent.ddpg.actor_final_bound=0",
]


@pytest.fixture(scope="module")
def with_demos(smoke_builds, tmp_path_factory):
    """A copy of the smoke world model plus 3 planner demonstrations, written with 2 workers."""
    import shutil

    from worldmodel.config import compose

    root = tmp_path_factory.mktemp("demos")
    shutil.copytree(smoke_builds("rnn"), root, dirs_exist_ok=True)
    base = [f"paths.data_root={root}/data", f"paths.runs_root={root}/runs", "experiment=t", "scale=smoke", "threads=1"]
    demonstrate.run(compose("demonstrate", [*base, *DEMOS, "demos.num_workers=2"]))
    return root, base


def test_demonstrations_are_reproducible_and_in_the_rollout_schema(with_demos, stage_cfg, tmp_path):
    root, _ = with_demos
    demonstrate.run(stage_cfg("demonstrate", *DEMOS, "demos.num_workers=1", root=tmp_path))
    a, b = RolloutStore(root / "data/t/demos"), RolloutStore(tmp_path / "data/t/demos")
    assert validate(root / "data/t/demos")[0] == 3
    for i in range(3):
        for key in ("seg", "speed", "action", "reward_r2"):
            np.testing.assert_array_equal(a.read(i, key), b.read(i, key))
        spec = json.loads(a.attrs(i)["scenario"])
        assert 15.0 <= spec["ego_speed"] <= 30.0 and 0.25 <= spec["ttc"] <= 1.1  # the focus mix
    # the planner steers in some demonstrations and brakes in all of them: the store holds its actions
    actions = np.concatenate([a.read(i, "action")[:-1] for i in range(3)])
    assert actions[:, 1].min() < -0.5


def test_demonstrations_become_the_transitions_a_live_run_would_give(with_demos, tmp_path):
    """The stored episode, encoded offline, equals the agent inputs of the same planner episode run live through
    WorldModelView; the stored actions become the actor outputs that ask for them."""
    import shutil

    from envs.planner import PrivilegedPlanner
    from worldmodel.agent_obs import WorldModelView
    from worldmodel.common import make_env
    from worldmodel.config import compose, teacher_settings

    root, base = with_demos
    shutil.copytree(root, tmp_path, dirs_exist_ok=True)
    base = [f"paths.data_root={tmp_path}/data", f"paths.runs_root={tmp_path}/runs", *base[2:]]
    cfg = compose("train_agent", [*base, *DEMOS, *LEARNER, "agent.total_steps=0", "agent.bc_pretrain_steps=50"])
    encoder = loading.load_world_model(cfg)  # speed and the frame's hazard profiles, as LEARNER asks
    assert encoder.dim == 2 * encoder.latent_dim + 1 + encoder.frame_view.dim
    action_map = ActionMap("brake", "grip")
    demos, info = imitation.demonstration_buffer(cfg, encoder, action_map, "r2", cfg.agent)
    store = RolloutStore(tmp_path / "data/t/demos")
    assert info == {"episodes": 3, "transitions": sum(int(store.attrs(i)["n_steps"]) for i in range(3))}

    # episode 0 live: the planner drives, the agent's view encodes what it sees
    spec = demonstrate.spec_of(demonstrate.demo_settings(cfg), 0)
    sim = make_env(cfg, horizon_after_ttc_s=3.0)
    view = WorldModelView(sim, encoder, ActionMap())  # the identity: the planner's actions go in unchanged
    states, actions = [], []
    planner = PrivilegedPlanner.from_settings(**teacher_settings(cfg))
    obs, _ = view.reset(options={"scenario": spec})
    states.append(obs)
    planner.reset(spec.seed)
    planner.bind(sim)
    done = False
    while not done:
        a = planner.act(None, None)
        obs, _, terminated, truncated, _ = view.step(a)
        states.append(obs)
        actions.append(a)
        done = terminated or truncated
    n = len(actions)
    assert n == int(store.attrs(0)["n_steps"])
    first = demos.obs[:n]  # episode 0's transitions come first, in order (one-step returns)
    np.testing.assert_allclose(first, np.stack(states[:-1]), atol=1e-5)
    np.testing.assert_allclose(demos.next_obs[:n], np.stack(states[1:]), atol=1e-5)
    speed = store.read(0, "speed")
    for t in (0, n // 2, n - 1):
        np.testing.assert_allclose(demos.actions[t], action_map.from_env(actions[t], speed[t]), atol=1e-6)
    np.testing.assert_allclose(demos.rewards[:n], store.read(0, "reward_r2")[:n])

    # the frame view's second half is the previous frame's first half, zero at the first frame
    half = encoder.frame_view.dim // 2
    assert not first[0, -half:].any()
    np.testing.assert_array_equal(first[1:, -half:], first[:-1, -2 * half : -half])

    # cloning runs and moves the actor away from its zero start
    train_agent.run(cfg)
    actor, _ = loading.load_actor(cfg, artifacts.AgentId.of(cfg))
    with torch.no_grad():
        assert actor(torch.from_numpy(first)).abs().max() > 0.01
    # evaluation rebuilds the agent's own input from its checkpoint, whatever the current config says
    from worldmodel.config import compose as compose_eval
    from worldmodel.policies import policy_for

    policy, _, _ = policy_for(compose_eval("evaluate", base), artifacts.AgentId.of(cfg).key)
    assert policy.encoder.dim == encoder.dim
    policy.reset(0)
    obs = {"seg": store.read(0, "seg")[0], "speed": speed[:1]}
    with torch.no_grad():
        u = actor(torch.from_numpy(first[:1]))[0].numpy()
    np.testing.assert_allclose(policy.act(obs, None), action_map.to_env(u, float(speed[0])), atol=1e-5)


def test_missing_or_absent_demonstrations_are_clear_errors(stage_cfg, experiment_copy):
    root = experiment_copy("rnn")
    with pytest.raises(StageError, match="agent.demo_share"):
        train_agent.run(stage_cfg("train_agent", "agent.demo_share=0.25", root=root))
    with pytest.raises(StageError, match="python -m worldmodel.demonstrate"):
        train_agent.run(stage_cfg("train_agent", *DEMOS, "agent.bc_pretrain_steps=10", root=root))


def test_variants_are_named_apart_and_parsed_back():
    paper = artifacts.AgentId("r2", 0)
    variant = artifacts.AgentId("r2", 1, "fd")
    assert (paper.key, variant.key) == ("agent_r2/seed0", "agent_r2_fd/seed1")
    assert artifacts.AgentId.parse(variant.key) == variant and artifacts.AgentId.parse(paper.key) == paper
    with pytest.raises(ValueError, match="does not name an agent"):
        artifacts.AgentId.parse("agent_r3_fd/seed0")


def test_pipeline_plans_demonstrations_and_preset_variants(stage_cfg):
    from worldmodel import pipeline

    plain = [s.name for s in pipeline.steps(stage_cfg("pipeline", "agents=[ddpg]"))]
    assert plain == ["collect", "vae", "rnn", "agent_r1", "agent_r2", "eval"]  # the paper's pipeline, unchanged
    # the default adds the chooser and the counterfactual actor, R2 only (their presets' agent.rewards), with no
    # demonstrations
    default = [s.name for s in pipeline.steps(stage_cfg("pipeline"))]
    assert default == [
        "collect", "vae", "rnn", "agent_r1", "agent_r2_chooser", "agent_r2_counterfactual", "agent_r2", "eval"
    ]  # fmt: skip
    with pytest.raises(StageError, match="demos.episodes"):
        pipeline.steps(stage_cfg("pipeline", "agents=[ddpg,dag]"))
    steps = pipeline.steps(stage_cfg("pipeline", "agents=[ddpg,dag]", "demos.episodes=3"))
    names = [s.name for s in steps]
    assert names == ["collect", "vae", "rnn", "demos", "agent_r1", "agent_r2_dag", "agent_r2", "eval"]  # dag: R2 only
    dag = next(s for s in steps if s.name == "agent_r2_dag")
    # the preset wins over the scale (smoke sets total_steps 300; the preset clones only)
    assert dag.changes["agent"].total_steps == 0 and dag.changes["agent"].dagger_rounds == 2
    assert dag.changes["agent"].ddpg.batch_size == 16  # a scale key the preset leaves alone
    with pytest.raises(StageError, match="no preset"):
        pipeline.steps(stage_cfg("pipeline", "agents=[nosuch]"))


def test_minibatches_mix_demonstrations_in_the_asked_share():
    from worldmodel.models.ddpg import ReplayBuffer

    own, demos = ReplayBuffer(50, 3, 2), ReplayBuffer(50, 3, 2)
    for _ in range(20):
        own.add(np.zeros(3), np.zeros(2), 0.0, np.zeros(3), False)
        demos.add(np.ones(3), np.ones(2), -1.0, np.ones(3), True)
    batch = imitation.mixed_batch(own, demos, 16, 0.25, np.random.default_rng(0))
    assert batch["obs"].shape == (16, 3) and batch["demo"].sum().item() == 4
    # the mask marks exactly the demonstration samples
    np.testing.assert_array_equal(batch["obs"][:, 0].numpy(), batch["demo"].numpy())
    assert "demo" in imitation.mixed_batch(own, None, 16, 0.25, np.random.default_rng(0))
    assert imitation.mixed_batch(own, None, 16, 0.25, np.random.default_rng(0))["demo"].sum() == 0


def test_focus_share_draws_training_episodes_from_the_focus_mix(stage_cfg):
    paper = ddpg_learner.reset_options(stage_cfg("train_agent"), 7)
    assert set(paper) == {"seed"}
    cfg = stage_cfg("train_agent", "agent.focus_share=1.0")
    focus = [ddpg_learner.reset_options(cfg, e) for e in range(20)]
    specs = [f["options"]["scenario"] for f in focus]
    assert all(15.0 <= s.ego_speed <= 30.0 and 0.25 <= s.ttc <= 1.1 for s in specs)
    assert sum(s.hazard != "none" for s in specs) >= 12  # 85 % hazards
    again = ddpg_learner.reset_options(cfg, 3)
    assert again["options"]["scenario"] == specs[3]  # depends only on (seed, episode)
