"""The LIDAR chooser on family kim (worldmodel/families/kim/chooser.py, agent=kim_chooser): its outcome on labelled
braking states is what it does in closed loop, which is what lets its scorer be chosen, and its ceiling read,
without simulating (docs/results/kim/README.md); and it trains through train_agent and is evaluated with the family."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from envs import StraightLineBraking
from envs.chooser import switch_choice
from worldmodel.config import compose
from worldmodel.families.kim import chooser as kim_chooser
from worldmodel.families.kim import system as kim

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
    return cfg, specs, kim_chooser.label_episodes(cfg, specs, DECIDE_STEPS)


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
    see = kim.observer(cfg, kim_chooser.REWARD)
    moves = kim_chooser.candidates(env.step_s)
    chooser = kim_chooser.chooser_policy(see, scorer, DECIDE_STEPS, margin, moves, "chooser")
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


def test_train_agent_fits_the_chooser_once_labelled_and_the_family_evaluation_drives_every_seed(tmp_path):
    """train_agent agent=kim_chooser for two seeds: the labels are made once, in the experiment's data folder, and
    the second seed reads them; each seed's folder holds its checkpoint and the provenance the pipeline compares, so
    the pipeline finds both complete and a rerun keeps the fitted scorer; a changed setting makes the run stale.
    Then evaluate.family=kim drives each seed in closed loop beside braking, one row set per seed; the Euro NCAP
    bank, whose kim group acts from each test's start, does not."""
    import csv

    from worldmodel import evaluate, pipeline, train_agent
    from worldmodel.artifacts import AgentId

    base = [f"paths.data_root={tmp_path}/data", f"paths.runs_root={tmp_path}/runs", "experiment=k", "scale=smoke"]

    def cfg(stage, *overrides):
        return compose(stage, [*base, "threads=1", *overrides])

    first = train_agent.run(cfg("train_agent", "agent=kim_chooser"))
    (stored,) = (tmp_path / "data/k/kim_chooser_labels").iterdir()
    made = stored.stat().st_mtime_ns
    second = train_agent.run(cfg("train_agent", "agent=kim_chooser", "seed=1"))
    assert stored.stat().st_mtime_ns == made  # seed 1 labelled nothing
    assert first["labelled_episodes"] == second["labelled_episodes"] == 6  # scale=smoke's
    assert first["labelled_states"] == second["labelled_states"]
    assert 1 <= first["kept_epoch"] <= 3

    run_dir = tmp_path / "runs/k/agent_kim_unaware_kim_chooser/seed0"
    assert {"last.pt", "metrics.json", "provenance.json"} <= {p.name for p in run_dir.iterdir()}
    steps = pipeline.steps(cfg("pipeline", "agents=[kim_chooser]", "seeds=[0,1]"))
    mine = [s for s in steps if s.agent is not None and s.agent.variant == "kim_chooser"]
    assert [s.agent for s in mine] == [AgentId("kim_unaware", s, "kim_chooser") for s in (0, 1)]
    pipeline_cfg = cfg("pipeline", "agents=[kim_chooser]")
    for step in mine:
        assert pipeline.status(OmegaConf.merge(pipeline_cfg, step.changes), step) == ("complete", [])
    saved = (run_dir / "last.pt").stat().st_mtime_ns
    assert train_agent.run(cfg("train_agent", "agent=kim_chooser", "resume=true")) == first
    assert (run_dir / "last.pt").stat().st_mtime_ns == saved  # kept, not refitted
    changed = cfg("pipeline", "agent=kim_chooser", "agents=[kim_chooser]", "agent.kim_chooser.margin=0.5")
    (step,) = [s for s in pipeline.steps(changed) if s.agent == AgentId("kim_unaware", 0, "kim_chooser")]
    assert pipeline.status(OmegaConf.merge(changed, step.changes), step) == ("stale", ["its config changed"])

    evaluate.run(cfg("evaluate", "evaluate.family=kim", "evaluate.kim.policies=[braking]"))
    rows = list(csv.DictReader(open(tmp_path / "runs/k/eval_kim/results.csv")))
    trials = sorted((r["scenario"], r["trial"]) for r in rows if r["policy"] == "braking")
    assert len(trials) == len(kim.bank(cfg("evaluate").evaluate.kim))  # every trial of the bank, once
    for seed in ("0", "1"):
        chooser = [r for r in rows if r["policy"] == "agent_kim_unaware_kim_chooser" and r["policy_seed"] == seed]
        assert sorted((r["scenario"], r["trial"]) for r in chooser) == trials
    # a takeover policy: the NCAP group that acts from each test's start leaves it out
    assert [p.name for p, *_ in kim.ncap_policies(cfg("evaluate"))] == ["aeb3m"]
