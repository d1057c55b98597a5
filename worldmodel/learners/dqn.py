"""A DQN (``worldmodel.models.dqn.DQN``: DQN or Double DQN, with its replay and trauma memories) as a ``Learner``
of the training loop (learners/loop.py). Chae et al.'s and Merola et al.'s families train it
(worldmodel/families/)."""

from __future__ import annotations

from collections.abc import Callable, Mapping


class DQNLearner:
    """Epsilon-greedy acting over discrete actions; every transition remembered, and into the trauma memory too
    where ``trauma_of(terminated, info)`` says so (None: none goes there); an update per step once warmed up."""

    def __init__(self, agent, trauma_of: Callable[[bool, dict], bool] | None = None):
        self.agent, self.trauma_of = agent, trauma_of

    @property
    def steps(self) -> int:
        return self.agent.steps

    def act(self, obs, explore: bool) -> int:
        return self.agent.act(obs, explore=explore)

    def observe(self, obs, action, reward: float, next_obs, terminated: bool, truncated: bool, info: dict) -> None:
        trauma = False if self.trauma_of is None else self.trauma_of(terminated, info)
        self.agent.remember(
            obs, action, reward, next_obs, terminated, trauma=trauma, episode_end=terminated or truncated
        )

    def update(self) -> Mapping[str, float] | None:
        return self.agent.update()

    def state_dict(self) -> dict:
        return {"agent": self.agent.state_dict()}

    def load_state_dict(self, state: Mapping) -> None:
        self.agent.load_state_dict(state["agent"])
