"""experiments/kim_chooser.py: the chooser's outcome on labelled braking states is what it does in closed loop, which
is what lets its scorer be chosen, and its ceiling read, without simulating (docs/results/kim/README.md)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs import StraightLineBraking
from envs.chooser import switch_choice
from experiments import kim_chooser
from worldmodel.config import compose
from worldmodel.peers import kim

DECIDE_STEPS = 3


def test_the_offline_rule_brakes_until_the_first_step_where_a_candidate_wins():
    cost = np.array([[5.0, 7.0, 0.0], [5.0, 0.0, 9.0], [8.0, 0.0, 0.0]])
    episode = np.array([0, 0, 1])
    scores = np.array([[5.0, 6.0, 5.5], [5.0, 1.0, 9.0], [0.0, 1.0, 1.0]])
    # episode 0: braking is cheapest at step 0; at step 1 candidate 1 wins, and its exact cost there is what counts
    # episode 1: braking is predicted cheapest, so the outcome is braking's own cost
    assert kim_chooser.outcomes(cost, scores, episode, margin=0.0).tolist() == [0.0, 8.0]
    # a switch must win by more than the margin: none does, both episodes brake
    assert kim_chooser.outcomes(cost, scores, episode, margin=4.0).tolist() == [5.0, 8.0]


def late_switches(data: dict, predicted: np.ndarray, margin: float) -> int:
    """Episodes whose first switch at ``margin`` comes after decision step 0."""
    late = 0
    for e in np.unique(data["episode"]):
        rows = np.flatnonzero(data["episode"] == e)
        steps = [data["step"][r] for r in rows if switch_choice(predicted[r], margin) is not None]
        late += bool(steps) and steps[0] > 0
    return late


@pytest.fixture(scope="module")
def labelled():
    cfg = compose("train_agent", ["agent=ddpg_kim", "scale=smoke", "threads=1", "evaluate.kim.trials=3"])
    specs = kim.bank(cfg.evaluate.kim)
    return cfg, specs, kim_chooser.labels(cfg, specs, DECIDE_STEPS)


def test_labels_hold_braking_and_every_candidate_at_each_decision_step(labelled):
    _, specs, data = labelled
    n = len(data["view"])
    assert data["cost"].shape == (n, len(kim_chooser.candidates()))
    assert sorted(set(data["episode"])) == list(range(len(specs)))
    assert (data["cost"] >= 0).all()
    # every episode is labelled from its first step, steps in order
    for e in range(len(specs)):
        assert data["step"][data["episode"] == e].tolist() == list(range(int((data["episode"] == e).sum())))


def test_offline_outcomes_are_the_closed_loop_ones(labelled):
    cfg, specs, data = labelled
    torch.manual_seed(0)  # an untrained scorer: its arbitrary costs make it switch, which is what is checked
    scorer = kim_chooser.Scorer(data["view"].shape[1] + DECIDE_STEPS, data["cost"].shape[1])
    with torch.no_grad():
        predicted = scorer(torch.from_numpy(kim_chooser.features(data, DECIDE_STEPS))).numpy()
    # a margin at which some episodes switch after the first step, where the view holds earlier scans and actions
    margin = max(np.r_[predicted[:, 0] - predicted.min(1)], key=lambda m: late_switches(data, predicted, m))
    assert late_switches(data, predicted, margin) >= 1
    offline = kim_chooser.outcomes(data["cost"], predicted, data["episode"], margin)
    env = kim.family_env(cfg, kim_chooser.REWARD)
    chooser = kim_chooser.chooser_policy(cfg, scorer, DECIDE_STEPS, margin, env.step_s)
    seen = []  # what the scorer reads in closed loop, decision by decision
    hook = scorer.register_forward_pre_hook(lambda _, args: seen.append(args[0].numpy().copy()))
    rows = kim.run_policy(env, chooser, specs)
    hook.remove()
    braking = kim.run_policy(env, StraightLineBraking(), specs)
    env.close()
    np.testing.assert_allclose([r["iss_kmh"] for r in rows], offline, rtol=1e-5)
    # it read exactly the labelled features, up to and including each episode's switch
    visited = []
    for e in np.unique(data["episode"]):
        for r in np.flatnonzero(data["episode"] == e):
            visited.append(r)
            if switch_choice(predicted[r], margin) is not None:
                break
    np.testing.assert_array_equal(np.concatenate(seen), kim_chooser.features(data, DECIDE_STEPS)[visited])
    # braking's outcome is each episode's first label of candidate 0
    first = np.flatnonzero(np.r_[True, np.diff(data["episode"]) != 0])
    np.testing.assert_allclose([r["iss_kmh"] for r in braking], data["cost"][first, 0], rtol=1e-5)
