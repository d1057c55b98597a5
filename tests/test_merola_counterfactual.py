"""The counterfactual-cost Q-learner on family merola (worldmodel/families/merola/counterfactual.py,
agent=counterfactual_merola): its labels are exact returns of Merola's nine actions held as shifts, seen from the
view the evaluated policy reads; its critic learns to order them; it trains through train_agent, chooses by its
critic, and is evaluated with the family."""

from __future__ import annotations

import json

import numpy as np
import pytest

from envs.counterfactual import BRAKE, Shift, shift_cost
from envs.merola import sample as sample_merola
from envs.rollout import rollout
from worldmodel import artifacts, counterfactual, evaluate, train_agent
from worldmodel.config import CounterfactualConfig, validate
from worldmodel.families.merola import counterfactual as merola_counterfactual
from worldmodel.families.merola import system as merola

# the preset keeps its labelled episodes and minibatches at every scale; the smoke scale's, passed as a user would.
# Two decisions and a DAgger round (the preset decides once), so that the policy's own states are labelled too.
# The true state as the view: no world model to build (the frames' view is the resume test's, test_resume.py)
AGENT = (
    *("agent=counterfactual_merola", "obs=privileged"),
    *("agent.counterfactual.decisions=2", "agent.counterfactual.dagger_rounds=1"),
    *("agent.counterfactual.episodes=6", "agent.counterfactual.dagger_episodes=2"),
    "agent.counterfactual.critic_steps=60",
)


def test_a_shift_that_releases_lets_go_of_the_brake_only_at_a_standstill_and_is_then_not_charged():
    shift = Shift(0.5, 1.0, 2, release=True)
    assert np.array_equal(shift.action(0, 0.0), [0.5, 1.0]) and np.array_equal(shift.action(3, 0.0), [-0.5, 1.0])
    assert np.array_equal(shift.action(4, 0.1), BRAKE) and np.array_equal(shift.action(4, None), BRAKE)
    assert np.array_equal(shift.action(4, 0.0), [0.0, 0.0])
    assert np.array_equal(Shift(0.5, 1.0, 2).action(4, 0.0), BRAKE), "without release the tail brakes on"
    # on the simulator: braking that lets go stands still uncharged, braking on pays Merola's 5 a step
    from worldmodel.config import compose

    env = merola.family_env(compose("train_agent", ["agent=ddqn_merola", "scale=smoke"]), camera=False)
    spec = sample_merola(np.random.default_rng(3), "lead_brake")
    returns = {}
    for release in (False, True):
        env.reset(options={"scenario": spec})
        twin = env.planning_twin()
        cost, _ = shift_cost(twin, env.snapshot(), Shift(0.0, -1.0, 1, release), None, reward="merola")
        returns[release] = (-cost, twin.ego.v)
    env.close()
    assert returns[True][1] == returns[False][1] == 0.0, "both stop before the episode ends"
    assert returns[True][0] - returns[False][0] >= 5.0 * 10, returns


@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    """Round 0's labels of 40 braking episodes, the nine actions at the start (the preset's one decision: each run
    to the episode's end, no second decision to re-simulate, so labelling is cheap)."""
    from worldmodel.config import compose

    root = tmp_path_factory.mktemp("merola_counterfactual")
    overrides = [
        *(f"paths.data_root={root}/data", f"paths.runs_root={root}/runs", "experiment=t", "scale=smoke"),
        *("threads=1", *AGENT, "agent.counterfactual.episodes=40", "agent.counterfactual.decisions=1"),
    ]
    cfg = compose("train_agent", overrides)
    typed = validate(cfg)
    source = merola_counterfactual.NineActionLabels(cfg, typed, "merola_safe", root / "run")
    return cfg, typed, source.round_data(0, typed.agent.counterfactual.episodes, None, None)


def test_labels_are_the_return_of_each_of_the_nine_actions_from_braking_states(labelled):
    cfg, typed, data = labelled
    c = typed.agent.counterfactual
    assert sorted(set(data["episode"])) == list(range(40))
    assert np.array_equal(data["u"], np.broadcast_to(merola_counterfactual.CODES, data["u"].shape))
    assert not data["chosen"].any(), "braking drove round 0"
    assert (data["costs"] > 100).any() and (data["costs"] < 0).any(), "no crash or no clear run labelled"
    # re-simulating one label from the scenario's start gives the same float
    row = len(data["t"]) - 1
    e, k = int(data["episode"][row]), int(np.argmax(data["costs"][row]))
    env = merola.family_env(cfg, camera=False, reward="merola_safe")
    spec = sample_merola(np.random.default_rng([0, merola_counterfactual.MEROLA_COUNTERFACTUAL_LABELS, 0, e]))
    env.reset(options={"scenario": spec})
    shifts = merola_counterfactual.space(c.hold_s[0], env.step_s)
    braking = shifts.shift(np.zeros(3))
    for t in range(int(data["t"][row])):
        env.step(braking.action(t, env.ego.v))
    d = int(np.sum(data["episode"][: row + 1] == e)) - 1
    interval = None if d == c.decisions - 1 else c.interval(env.step_s)
    nine = [shifts.shift(u) for u in merola_counterfactual.CHOICES]
    twin = env.planning_twin()
    cost, _ = shift_cost(twin, env.snapshot(), nine[k], interval, nine, "merola_safe")
    env.close()
    assert cost == pytest.approx(float(data["costs"][row, k]), abs=1e-4)


def test_the_fitted_critic_orders_held_out_actions_better_than_a_constant(labelled):
    _, typed, data = labelled
    held = data["held"]
    assert 0 < held.sum() < len(held)
    fit = CounterfactualConfig(**{**vars(typed.agent.counterfactual), "critic_steps": 400, "batch_size": 64})
    critic, figures = counterfactual.fit_critic(
        data["x"], data["u"], data["costs"], data["state"], held, fit, seed=0, round_=0
    )
    assert figures["pairwise_order"] > 0.6, figures
    choices = merola_counterfactual.CODES
    chosen = counterfactual.choice_figures(critic, data["x"][held], data["u"][held], data["costs"][held], choices, fit)
    assert chosen["exact_cost_best"] <= chosen["exact_cost_chosen"], chosen


def test_trains_through_train_agent_chooses_on_the_view_it_is_labelled_on_and_is_evaluated(stage_cfg):
    """The evaluated policy, rebuilt from the checkpoint, sees at its decisions exactly the views that a labelling
    round driven by the same checkpoint records, and chooses the same actions; the family's evaluation runs it."""
    metrics = train_agent.run(stage_cfg("train_agent", *AGENT))
    assert metrics["learner"] == "counterfactual" and set(metrics["labelled_episodes"]) == {"round0", "round1"}
    cfg = stage_cfg("train_agent", *AGENT)
    typed = validate(cfg)
    (agent,) = artifacts.trained_agents(cfg, family="merola")
    policy = merola.load_policy(cfg, agent)
    state = merola.loading.load_agent_state(cfg, agent, "last")
    data = merola_counterfactual.label_shard(cfg, typed, "merola_safe", 1, 0, 1, merola_counterfactual.decision(state))
    seen, chose = [], policy.decide
    policy.decide = lambda x, d: seen.append(np.asarray(x)) or chose(x, d)
    env = merola.family_env(cfg, camera=False, reward="merola_safe")
    rollout(
        env, policy, sample_merola(np.random.default_rng([0, merola_counterfactual.MEROLA_COUNTERFACTUAL_LABELS, 1, 0]))
    )
    env.close()
    assert len(seen) == len(data["view"]) > 1
    assert np.array_equal(np.stack(seen), data["view"])
    assert np.array_equal(np.stack(policy.chosen), data["chosen"])
    assert {tuple(u) for u in data["chosen"]} <= {tuple(u) for u in merola_counterfactual.CHOICES}
    ev = stage_cfg(
        "evaluate",
        *("evaluate.family=merola", "evaluate.merola.trials=2", "evaluate.merola.world_model_agents=false"),
        "evaluate.merola.policies=[braking]",
    )
    evaluate.run(ev)
    out = artifacts.eval_dir(ev)
    rows = (out / "results.csv").read_text().splitlines()
    assert sum(agent.policy in r for r in rows) == 6, "2 trials of each of 3 scenarios"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["policies"][agent.policy]["group"] == "counterfactual"
