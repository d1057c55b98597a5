"""The one training loop (worldmodel/learners/loop.py) keeps its contract. On Chae's real DQN and family env: a run
that saves only between episodes stops only there, and one that saves inside episodes (the paper's) stops at the
step it is asked to and goes on as if it had never stopped. On the counterfactual actor's critic, a learner that
fits labelled rows: a fit stops when asked, goes on from its state as if it had never stopped, and keeps the weights
of its best held-out check."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs.chae import BRAKE_LEVELS, brake_action
from envs.privileged import PRIVILEGED_DIM
from worldmodel.artifacts import AgentId
from worldmodel.config import CounterfactualConfig
from worldmodel.counterfactual import ActorFit, CriticFit
from worldmodel.families.chae.observe import family_env, observer
from worldmodel.families.chae.train import bumped, episode_scenario
from worldmodel.families.common import DQNEpisodes, dqn_config
from worldmodel.learners.dqn import DQNLearner
from worldmodel.learners.loop import Callbacks, HeldOutChecks, TrainingLoop, fit
from worldmodel.models.counterfactual import CostCritic, ShiftActor
from worldmodel.models.dqn import DQN
from worldmodel.training import GracefulStop, TrainingRun


class Lengths(Callbacks):
    """Each finished episode's length and the loop's episode count after it."""

    def __init__(self):
        self.ended: list[tuple[int, int]] = []

    def on_episode(self, loop, outcome, ret, length):
        self.ended.append((loop.episode, length))


def run_chae(cfg, mid_episode: bool, *budgets):
    """A DQN on family chae in the loop, run to each of ``budgets`` (callables of the loop) in turn; returns the
    loop, its callbacks and the learner's state."""
    with TrainingRun.for_agent(cfg, AgentId.of(cfg)) as run_:
        see = observer(cfg, "pedestrian_history")
        env = family_env(cfg, see.camera)
        learner = DQNLearner(DQN(see.dim, len(BRAKE_LEVELS), dqn_config(cfg), seed=0), trauma_of=bumped)
        episodes = DQNEpisodes(env, see, lambda k: episode_scenario(0, k), brake_action)
        seen = Lengths()
        loop = TrainingLoop(learner, episodes, run_, seen, mid_episode=mid_episode)
        loop.begin()
        for budget in budgets:
            loop.run(lambda b=budget: b(loop))
        env.close()
    return loop, seen, learner.state_dict()["agent"]


def test_a_run_that_saves_between_episodes_stops_only_there(stage_cfg):
    cfg = stage_cfg("train_agent", "agent=dqn_chae", "agent.dqn.warmup_steps=5")
    loop, seen, _ = run_chae(cfg, False, lambda loop: loop.step >= 3)
    (episode, length), *_ = seen.ended
    assert length > 3, "Chae's episodes last more than three 0.1 s steps"
    assert (loop.episode, loop.step, loop.obs) == (1, length, None) and episode == 1


def test_a_run_that_saves_inside_episodes_stops_at_its_step_and_goes_on_unchanged(stage_cfg):
    cfg = stage_cfg("train_agent", "agent=dqn_chae", "agent.dqn.warmup_steps=5")
    stopped, seen, _ = run_chae(cfg, True, lambda loop: loop.step >= 3)
    assert (stopped.step, stopped.episode, seen.ended) == (3, 0, [])
    assert stopped.obs is not None and stopped.length == 3

    cfg = stage_cfg("train_agent", "agent=dqn_chae", "agent.dqn.warmup_steps=5", root=stopped.run_.dir / "again")
    straight, seen_straight, whole = run_chae(cfg, False, lambda loop: loop.episode >= 2)
    cfg = stage_cfg("train_agent", "agent=dqn_chae", "agent.dqn.warmup_steps=5", root=stopped.run_.dir / "split")
    split, seen_split, parts = run_chae(cfg, True, lambda loop: loop.step >= 3, lambda loop: loop.episode >= 2)
    assert seen_split.ended == seen_straight.ended and split.step == straight.step
    for key in ("q_network", "target_network"):
        for name, value in whole[key].items():
            assert torch.equal(value, parts[key][name]), f"{key}.{name} differs after stopping inside an episode"
    assert whole["rng"] == parts["rng"] and whole["updates"] == parts["updates"] > 0


def critic_fit(seed: int = 0) -> CriticFit:
    """A fresh critic's fit on 64 labelled states of 5 proposals each (random rows: the fit's own steps are tested)."""
    rows = np.random.default_rng(7)
    x, u = rows.normal(size=(64, 6)).astype(np.float32), rows.uniform(-1, 1, (64, 5, 3)).astype(np.float32)
    costs, state = rows.random((64, 5)).astype(np.float32), rows.normal(size=(64, PRIVILEGED_DIM)).astype(np.float32)
    c = CounterfactualConfig(critic_members=2, critic_hidden=(16,), batch_size=8)
    torch.manual_seed(seed)
    critic = CostCritic(6, c.critic_members, c.critic_hidden)
    xt, ut, yt, st = (torch.from_numpy(a) for a in (x, u, costs, state))
    critic.norm.fit(xt)
    return CriticFit(critic, xt, ut, yt, st, c, np.random.default_rng(seed))


def actor_fit(seed: int = 0) -> ActorFit:
    """A fresh actor's fit against a critic fitted for 20 minibatches, searching 4 random shifts a state (so that
    its torch generator is part of its state)."""
    critic = critic_fit()
    fit(critic, 20)
    c = CounterfactualConfig(critic_members=2, critic_hidden=(16,), batch_size=8, search=4)
    torch.manual_seed(seed)
    actor = ShiftActor(6, (16,))
    actor.norm.fit(critic.xt)
    draws = torch.Generator().manual_seed(seed)
    return ActorFit(actor, critic.critic, critic.xt, critic.xt, critic.st, c, np.random.default_rng(seed), draws)


class StopAt(Callbacks):
    def __init__(self, step: int):
        self.step, self.stop = step, GracefulStop()

    def on_step(self, loop):
        self.stop.requested = loop.step >= self.step


@pytest.mark.parametrize("make, module", [(critic_fit, "critic"), (actor_fit, "actor")])
def test_a_fit_stops_when_asked_and_goes_on_from_its_state_as_if_it_had_never_stopped(make, module):
    straight = make()
    assert fit(straight, 30)
    stopping = StopAt(12)
    first = make()
    assert not fit(first, 30, stopping, stop=stopping.stop) and first.steps == 12
    saved = first.state_dict()
    second = make(seed=1)  # other weights and draws, until the state is loaded
    second.load_state_dict(saved)
    assert fit(second, 30) and second.steps == 30
    whole, parts = getattr(straight, module).state_dict(), getattr(second, module).state_dict()
    for name, value in whole.items():
        assert torch.equal(value, parts[name]), f"{module} {name} differs after stopping at step 12"


def test_held_out_checks_keep_the_weights_of_the_best_check():
    learner = critic_fit()
    figures = iter([3.0, 1.0, 2.0])  # the second check, after 10 minibatches, is the best
    snapshots = {}

    class Snapshot(Callbacks):
        def on_step(self, loop):
            snapshots[loop.step] = {k: v.clone() for k, v in learner.critic.state_dict().items()}

    checks = HeldOutChecks(lambda: {"mse": next(figures)}, 5, 15, keep=learner.critic, best_of="mse")
    assert fit(learner, 15, checks, Snapshot())
    assert [step for step, _ in checks.history] == [5, 10, 15] and (checks.best_step, checks.best_figure) == (10, 1.0)
    assert not torch.equal(learner.critic.state_dict()["trunks.0.0.weight"], snapshots[10]["trunks.0.0.weight"])
    checks.restore()
    for name, value in learner.critic.state_dict().items():
        assert torch.equal(value, snapshots[10][name]), f"{name} is not the best check's"
