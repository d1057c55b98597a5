"""The one training loop (worldmodel/learners/loop.py) keeps its contract, on Chae's real DQN and family env: a run
that saves only between episodes stops only there, and one that saves inside episodes (the paper's) stops at the
step it is asked to and goes on as if it had never stopped."""

from __future__ import annotations

import torch

from envs.chae import BRAKE_LEVELS, brake_action
from worldmodel.artifacts import AgentId
from worldmodel.families.chae.observe import family_env, observer
from worldmodel.families.chae.train import bumped, episode_scenario
from worldmodel.families.common import DQNEpisodes, dqn_config
from worldmodel.learners.dqn import DQNLearner
from worldmodel.learners.loop import Callbacks, EpisodeLoop
from worldmodel.models.dqn import DQN
from worldmodel.training import TrainingRun


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
        loop = EpisodeLoop(learner, episodes, run_, seen, mid_episode=mid_episode)
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
