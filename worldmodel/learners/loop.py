"""The one training loop of every learner, ``TrainingLoop``. Those that learn by acting (the paper's DDPG and TD3,
Kim et al.'s LIDAR DDPG, Chae et al.'s DQN, Merola et al.'s DDQN) act, observe and update, episode after episode.
Those that learn from labelled rows (the chooser's scorer, the counterfactual actor's critic and actor, Kim et al.'s
LIDAR chooser, behaviour cloning) only update, one minibatch a step: ``fit`` runs them.

Three small interfaces meet here, so that a learner knows nothing of scenarios and a family nothing of replay
memories (docs/design.md §11):

- ``Learner``: updates, and saves and restores its state (network weights, optimisers, replay memory, random
  generators, its clock of steps). ``ActingLearner`` adds acting and observing a transition.
  ``learners/ddpg.py:DDPGLearner`` and ``learners/dqn.py:DQNLearner`` act; the fits are ``Learner``s.
- ``Episodes``: the family's side. How training episode k starts, and one step of it in the learner's terms (the
  observation it sees, its action mapped to the simulator's pedal and steering).
- ``Callbacks``: what the run does after a step and after an episode: TensorBoard, its learning curve,
  checkpoints, validations. ``Curves`` and ``HeldOutChecks`` are the fits' own.

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
    """What the loop drives: SB3's ``BaseAlgorithm`` cut down to a step, its state and its clock."""

    steps: int
    """the loop's clock: transitions observed (warm-up and exploration schedules run on it), or, for a learner
    that learns from labelled rows, minibatches taken"""

    def update(self) -> Mapping[str, float] | None:
        """One learning step, when one is due: its losses and statistics (floats or 0-d tensors), or None. A
        learner that learns from labelled rows draws its minibatch, steps and counts it here."""

    def state_dict(self) -> dict:
        """Everything a resumed run needs, as entries of the run's checkpoint."""

    def load_state_dict(self, state: Mapping) -> None:
        """Restore from a checkpoint that ``state_dict``'s entries went into."""


class ActingLearner(Learner, Protocol):
    """A learner that learns by acting: it acts, observes each transition (and counts it), then updates."""

    def act(self, obs, explore: bool) -> Any:
        """The action for ``obs``: exploring (training) or not (evaluation)."""

    def observe(self, obs, action, reward: float, next_obs, terminated: bool, truncated: bool, info: dict) -> None:
        """Remember one transition (and count it)."""


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

    def on_step(self, loop: TrainingLoop) -> None:
        """After every step (and after ``on_episode`` where the step ended one)."""

    def on_episode(self, loop: TrainingLoop, outcome: dict, ret: float, length: int) -> None:
        """After an episode: its outcome, return and length in steps. ``loop.episode`` already counts it."""


class TrainingLoop:
    """Act, step, observe, update; episode after episode, until the run's budget is spent or a stop is requested.
    Without ``episodes``, a learner that learns from labelled rows: update, step after step.

    ``run_``: the agent's ``TrainingRun``, whose stop and last checkpoint the loop heeds; a fit run outside one (a
    test, an experiment) passes ``stop`` (or None) and ``last`` (or None) instead.

    ``mid_episode``: the run saves inside episodes (a stop may come at any step, and the next episode starts as
    soon as one ends, so that a checkpoint holds no finished episode). Otherwise the loop stops only between
    episodes, and each starts when its first step is taken.
    """

    def __init__(
        self,
        learner: Learner,
        episodes: Episodes | None,
        run_,
        callbacks: Callbacks,
        *,
        episode: int = 0,
        mid_episode: bool = False,
        bar_unit: str = "step",
        stop=None,
        last=None,
    ):
        self.learner, self.episodes, self.run_, self.callbacks = learner, episodes, run_, callbacks
        self.episode, self.mid_episode, self.bar_unit = episode, mid_episode, bar_unit
        self.stop, self.last = (run_.stop, run_.last) if run_ is not None else (stop, last)
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
        ``mid_episode`` run or a fit); ``bar`` (tqdm) counts steps or episodes (``bar_unit``)."""
        stop = self.stop
        while not ((self.obs is None or self.mid_episode) and (until() or (stop is not None and stop.requested))):
            self.transition(bar)

    def transition(self, bar=None) -> None:
        """One step: of the episode in progress, and its end if it ends; or one update of a fit."""
        if self.episodes is None:
            self.learn()
            if bar is not None:
                bar.update(1)
            self.callbacks.on_step(self)
            return
        if self.obs is None:
            self.begin(self.episodes.start(self.episode))
        learner, obs = self.learner, self.obs
        action = learner.act(obs, explore=True)
        next_obs, reward, terminated, truncated, info = self.episodes.step(action)
        learner.observe(obs, action, reward, next_obs, terminated, truncated, info)
        self.ret += reward
        self.length += 1
        self.learn()
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

    def learn(self) -> None:
        """The learner's update, its losses kept for the callbacks, a non-finite one stopping the run."""
        losses = self.learner.update()
        if losses:
            self.losses = losses
            for key in CHECKED_LOSSES:
                if key in losses:
                    check_finite(float(losses[key]), key.replace("_", " "), self.step, self.last)


# ----------------------------------------------------------------------------- fitting labelled rows
def fit(learner: Learner, total: int, *callbacks: Callbacks, stop=None, last=None, bar=None) -> bool:
    """A learner that learns from labelled rows, updated until it has taken ``total`` minibatches or ``stop`` (a
    ``training.GracefulStop``, or None) is requested; ``callbacks`` in turn after each. ``last``: the checkpoint a
    non-finite loss names. Returns whether it took them all."""
    loop = TrainingLoop(learner, None, None, Together(*callbacks), stop=stop, last=last)
    loop.run(lambda: learner.steps >= total, bar)
    return learner.steps >= total


def fit_state(learner, modules: dict, draws=None) -> dict:
    """The state of a fit on labelled rows: its ``modules``' weights, its optimiser (``learner.opt``), its numpy
    generator (``learner.rng``), a torch generator ``draws`` where it has one, and its clock."""
    state = {name: module.state_dict() for name, module in modules.items()}
    state.update(optimizer=learner.opt.state_dict(), rng=learner.rng.bit_generator.state, steps=learner.steps)
    if draws is not None:
        state["draws"] = draws.get_state()
    return state


def load_fit_state(learner, state, modules: dict, draws=None) -> None:
    """``fit_state``'s inverse."""
    for name, module in modules.items():
        module.load_state_dict(state[name])
    learner.opt.load_state_dict(state["optimizer"])
    learner.rng.bit_generator.state = state["rng"]
    if draws is not None:
        draws.set_state(state["draws"])
    learner.steps = int(state["steps"])


class Together(Callbacks):
    """Several callbacks, in turn."""

    def __init__(self, *callbacks: Callbacks):
        self.callbacks = callbacks

    def on_step(self, loop: TrainingLoop) -> None:
        for callback in self.callbacks:
            callback.on_step(loop)

    def on_episode(self, loop: TrainingLoop, outcome: dict, ret: float, length: int) -> None:
        for callback in self.callbacks:
            callback.on_episode(loop, outcome, ret, length)


class Curves(Callbacks):
    """A fit's training losses: every ``every`` minibatches from the first, each update's losses are checked finite
    and written to TensorBoard (``writer``; None: checked only) as ``prefix + name`` at ``offset`` + the minibatch's
    index (from 0). A fit that runs after others in one run offsets its curves past theirs."""

    def __init__(self, writer, prefix: str, every: int = 50, offset: int = 0):
        self.writer, self.prefix, self.every, self.offset = writer, prefix, every, offset

    def on_step(self, loop: TrainingLoop) -> None:
        index = loop.step - 1
        if index % self.every:
            return
        for name, value in loop.losses.items():
            value = float(value)
            check_finite(value, f"{self.prefix}{name}", index, loop.last)
            if self.writer is not None:
                self.writer.add_scalar(f"{self.prefix}{name}", value, self.offset + index)


class HeldOutChecks(Callbacks):
    """A fit's checks on its held-out rows: every ``every`` minibatches and after the last (``total``), ``check()``'s
    figures, written to TensorBoard (``writer``; None: not written) as ``prefix + name`` at ``offset`` + the
    minibatch's index, and kept in ``history`` as (minibatches, figures).

    With ``keep`` (a module): the weights it had at the best figure ``best_of`` (the lowest, or the highest with
    ``higher_is_better``) are kept, and ``restore`` puts them back: the fit's early stopping."""

    def __init__(
        self,
        check: Callable[[], dict],
        every: int,
        total: int,
        writer=None,
        prefix: str = "",
        offset: int = 0,
        *,
        keep=None,
        best_of: str = "",
        higher_is_better: bool = False,
    ):
        self.check, self.every, self.total = check, every, total
        self.writer, self.prefix, self.offset = writer, prefix, offset
        self.keep, self.best_of, self.sign = keep, best_of, -1.0 if higher_is_better else 1.0
        self.history: list[tuple[int, dict]] = []
        self.best, self.best_step, self.best_state = float("inf"), 0, None

    def on_step(self, loop: TrainingLoop) -> None:
        step = loop.step
        if step % self.every and step != self.total:
            return
        figures = self.check()
        if self.writer is not None:
            for name, value in figures.items():
                self.writer.add_scalar(f"{self.prefix}{name}", value, self.offset + step - 1)
        self.history.append((step, figures))
        if self.keep is not None and self.sign * figures[self.best_of] < self.best:
            self.best, self.best_step = self.sign * figures[self.best_of], step
            self.best_state = {name: value.clone() for name, value in self.keep.state_dict().items()}

    @property
    def best_figure(self) -> float:
        """The best ``best_of`` seen (inf, or -inf with ``higher_is_better``, before any check)."""
        return self.sign * self.best

    def restore(self) -> None:
        """The kept weights back into ``keep`` (nothing, before any check)."""
        if self.best_state is not None:
            self.keep.load_state_dict(self.best_state)
