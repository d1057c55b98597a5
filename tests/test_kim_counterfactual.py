"""The counterfactual-cost DDPG on family kim (worldmodel/families/kim/counterfactual.py, agent=counterfactual_kim):
its labels are exact kim_unaware costs of the shifts, seen from the LIDAR view the evaluated policy reads; its critic
learns to order them; it trains through train_agent, resumes bit for bit, and is evaluated with the family."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs.counterfactual import shift_cost
from envs.rollout import rollout
from worldmodel import artifacts, counterfactual, train_agent
from worldmodel.config import CounterfactualConfig, validate
from worldmodel.families.kim import counterfactual as kim_counterfactual
from worldmodel.families.kim import system as kim
from worldmodel.models.counterfactual import ShiftActor

# the preset keeps its labelled episodes and minibatches at every scale; the smoke scale's, passed as a user would
AGENT = (
    "agent=counterfactual_kim",
    *("agent.counterfactual.episodes=4", "agent.counterfactual.dagger_episodes=2"),
    *("agent.counterfactual.critic_steps=60", "agent.counterfactual.actor_steps=40"),
)


@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    """Round 0's labels of 16 braking episodes of the training distribution, 6 shifts per decision."""
    from worldmodel.config import compose

    root = tmp_path_factory.mktemp("kim_counterfactual")
    overrides = [
        *(f"paths.data_root={root}/data", f"paths.runs_root={root}/runs", "experiment=t", "scale=smoke"),
        *("threads=1", *AGENT, "agent.counterfactual.episodes=16", "agent.counterfactual.proposals=6"),
    ]
    cfg = compose("train_agent", overrides)
    typed = validate(cfg)
    source = kim_counterfactual.LidarLabels(cfg, typed, root / "run")
    return cfg, typed, source.round_data(0, typed.agent.counterfactual.episodes, None, None)


def test_labels_are_the_kim_cost_of_each_shift_from_braking_states(labelled):
    cfg, typed, data = labelled
    c = typed.agent.counterfactual
    assert sorted(set(data["episode"])) == list(range(16))
    assert data["x"].shape == (len(data["t"]), kim.observer(cfg, "kim_unaware").dim + 1)
    assert (data["costs"] >= 0).all() and (data["costs"] > 0).any(), "no crash labelled: the check would be empty"
    # the first proposal at every decision is braking's (u = 0), the choice of the policy that drove
    assert not data["u"][:, 0].any() and not data["chosen"].any()
    # re-simulating one label from the scenario's own start gives the same float: braking, then the shift at t
    e = int(data["episode"][-1])
    row = np.flatnonzero(data["episode"] == e)[-1]
    env = kim.family_env(cfg, "kim_unaware")
    spec = kim.training_scenario(typed, kim_counterfactual.KIM_COUNTERFACTUAL_LABELS, 0, e, seed=c.label_seed)
    env.reset(options={"scenario": spec})
    for _ in range(int(data["t"][row])):
        env.step(np.array([0.0, -1.0], np.float32))
    twin, shift = env.planning_twin(), c.space(env.step_s).shift(data["u"][row, 1])
    d = int(np.sum(data["episode"][: row + 1] == e)) - 1
    interval = None if d == c.decisions - 1 else c.interval(env.step_s)
    cost, _ = shift_cost(twin, env.snapshot(), shift, interval, c.continuations(env.step_s), "kim_unaware")
    env.close()
    assert cost == pytest.approx(float(data["costs"][row, 1]), abs=1e-5)


def test_the_fitted_critic_orders_held_out_shifts_better_than_a_constant(labelled):
    _, typed, data = labelled
    held = data["held"]
    assert 0 < held.sum() < len(held)
    assert counterfactual.pairwise_order(np.zeros_like(data["costs"][held]), data["costs"][held]) == 0.5
    fit = CounterfactualConfig(**{**vars(typed.agent.counterfactual), "critic_steps": 400, "batch_size": 64})
    critic, figures = counterfactual.fit_critic(
        data["x"], data["u"], data["costs"], data["state"], held, fit, seed=0, round_=0
    )
    assert figures["pairwise_order"] > 0.6, figures
    actor = ShiftActor(data["x"].shape[1], (64, 64))
    figures = counterfactual.fit_actor(actor, critic, data["x"], data["x"], data["state"], held, fit, seed=0, round_=0)
    assert figures["objective"] < figures["braking_objective"], figures


def test_trains_through_train_agent_and_acts_on_the_view_it_is_labelled_on(stage_cfg):
    """The evaluated policy, rebuilt from the checkpoint, sees at its decisions exactly the LIDAR views that a
    labelling round driven by the same actor records, and so drives the same episode."""
    from worldmodel.counterfactual_labels import actor_decision
    from worldmodel.models.counterfactual import actor_from_state

    metrics = train_agent.run(stage_cfg("train_agent", *AGENT))
    assert metrics["learner"] == "counterfactual" and set(metrics["labelled_episodes"]) == {"round0", "round1"}
    cfg = stage_cfg("train_agent", *AGENT)
    typed = validate(cfg)
    state = torch.load(artifacts.agent_dir(cfg) / "last.pt", weights_only=False)
    assert state["obs"] == "lidar" and state["reward"] == "kim_unaware"
    decide = actor_decision(actor_from_state(state), typed.agent.counterfactual.decisions)
    data = kim_counterfactual.label_shard(cfg, typed, 1, 0, 1, decide)
    (agent,) = artifacts.trained_agents(cfg, family="kim")
    policy, camera = kim.load_policy(cfg, agent)
    assert not camera
    seen, chose = [], policy.decide
    policy.decide = lambda x, d: seen.append(np.asarray(x)) or chose(x, d)
    env = kim.family_env(cfg, "kim_unaware")
    rollout(env, policy, kim.training_scenario(typed, kim_counterfactual.KIM_COUNTERFACTUAL_LABELS, 1, 0, seed=0))
    env.close()
    assert len(seen) == len(data["view"]) > 1
    assert np.array_equal(np.stack(seen), data["view"])
    assert np.array_equal(np.stack(policy.chosen), data["chosen"])
