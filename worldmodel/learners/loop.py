"""The one training loop of every learner that learns by acting: the paper's DDPG (and TD3), Kim et al.'s LIDAR
DDPG, Chae et al.'s DQN and Merola et al.'s DDQN all run in ``EpisodeLoop``.

Three small interfaces meet here, so that a learner knows nothing of scenarios and a family nothing of replay
memories (docs/design.md §11):

- ``Learner``: acts, observes a transition, updates, and saves and restores its state (network weights,
  optimisers, replay memory, random generators, its clock of steps). ``learners/ddpg.py:DDPGLearner`` and
  ``learners/dqn.py:DQNLearner`` implement it.
- ``Episodes``: the family's side. How training episode k starts, and one step of it in the learner's terms (the
  observation it sees, its action mapped to the simulator's pedal and steering).
- ``Callbacks``: what the run does after a step and after an episode: TensorBoard, its learning curve,
  checkpoints, validations.

Exact resume needs nothing more of the loop: the learner's state, the episode count and, for a run that saves
inside episodes (``mid_episode``), the episode in progress (``training.EpisodeInProgress``) travel in the run's
checkpoint, and ``begin`` puts a resumed episode back.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Protocol

from ..common import check_finite

CHECKED_LOSSES = ("loss", "critic_loss", "actor_loss")  # a NaN here stops the run before it is saved


class Learner(Protocol):
    """An agent that learns by acting: SB3's ``BaseAlgorithm`` split into the four calls a loop makes."""

    steps: int
    """transitions observed: the clock of warm-up and exploration schedules"""

    def act(self, obs, explore: bool) -> Any:
        """The action for ``obs``: exploring (training) or not (evaluation)."""

    def observe(self, obs, action, reward: float, next_obs, terminated: bool, truncated: bool, info: dict) -> None:
        """Remember one transition (and count it)."""

    def update(self) -> Mapping[str, float] | None:
        """One learning step, when one is due: its losses and statistics, or None."""

    def state_dict(self) -> dict:
        """Everything a resumed run needs, as entries of the run's checkpoint."""

    def load_state_dict(self, state: Mapping) -> None:
        """Restore from a checkpoint that ``state_dict``'s entries went into."""


class Episodes(Protocol):
    """A family's training episodes, seen through the learner's eyes."""

    def start(self, episode: int) -> Any:
        """Start training episode ``episode`` (a function of the run's seed and ``episode`` only, so that a resumed
        run draws what an uninterrupted one would); its first observation."""

    def step(self, action) -> tuple:
        """Apply the learner's action: ``(obs, reward, terminated, truncated, info)``, ``info["outcome"]`` at the
        episode's end."""


class Callbacks:
    """What a run does as the loop goes; each hook is a no-op unless overridden."""

    def on_step(self, loop: EpisodeLoop) -> None:
        """After every step (and after ``on_episode`` where the step ended one)."""

    def on_episode(self, loop: EpisodeLoop, outcome: dict, ret: float, length: int) -> None:
        """After an episode: its outcome, return and length in steps. ``loop.episode`` already counts it."""


class EpisodeLoop:
    """Act, step, observe, update; episode after episode, until the run's budget is spent or a stop is requested.

    ``mid_episode``: the run saves inside episodes (a stop may come at any step, and the next episode starts as
    soon as one ends, so that a checkpoint holds no finished episode). Otherwise the loop stops only between
    episodes, and each starts when its first step is taken.
    """

    def __init__(
        self,
        learner: Learner,
        episodes: Episodes,
        run_,
        callbacks: Callbacks,
        *,
        episode: int = 0,
        mid_episode: bool = False,
        bar_unit: str = "step",
    ):
        self.learner, self.episodes, self.run_, self.callbacks = learner, episodes, run_, callbacks
        self.episode, self.mid_episode, self.bar_unit = episode, mid_episode, bar_unit
        self.obs, self.ret, self.length = None, 0.0, 0
        self.losses: Mapping[str, float] = {}

    @property
    def step(self) -> int:
        return self.learner.steps

    def begin(self, obs=None, ret: float = 0.0, length: int = 0) -> None:
        """The episode in progress: a resumed one at its saved step, or (``obs`` None) a new one, started now for a
        ``mid_episode`` run, at its first step otherwise."""
        if obs is None and self.mid_episode:
            obs = self.episodes.start(self.episode)
        self.obs, self.ret, self.length = obs, ret, length

    def run(self, until: Callable[[], bool], bar=None) -> None:
        """Steps until ``until()`` holds or a stop is requested, both checked between episodes (every step for a
        ``mid_episode`` run); ``bar`` (tqdm) counts steps or episodes (``bar_unit``)."""
        while not ((self.obs is None or self.mid_episode) and (until() or self.run_.stop.requested)):
            self.transition(bar)

    def transition(self, bar=None) -> None:
        """One step of the episode in progress, and its end if it ends."""
        if self.obs is None:
            self.begin(self.episodes.start(self.episode))
        learner, obs = self.learner, self.obs
        action = learner.act(obs, explore=True)
        next_obs, reward, terminated, truncated, info = self.episodes.step(action)
        learner.observe(obs, action, reward, next_obs, terminated, truncated, info)
        self.ret += reward
        self.length += 1
        losses = learner.update()
        if losses:
            self.losses = losses
            for key in CHECKED_LOSSES:
                if key in losses:
                    check_finite(losses[key], key.replace("_", " "), self.step, self.run_.last)
        self.obs = next_obs
        if bar is not None and self.bar_unit == "step":
            bar.update(1)
        if terminated or truncated:
            ret, length = self.ret, self.length
            self.episode += 1
            self.obs = None
            self.begin()
            if bar is not None and self.bar_unit == "episode":
                bar.update(1)
            self.callbacks.on_episode(self, info["outcome"], ret, length)
        self.callbacks.on_step(self)
