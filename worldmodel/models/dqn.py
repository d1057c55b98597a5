"""DQN with a trauma memory (Chae et al. 2017, "Autonomous braking system via deep reinforcement learning") and
Double DQN (van Hasselt et al. 2016, "Deep reinforcement learning with double Q-learning"; Merola et al. 2022).

One network Q(s, .) gives a value for each of ``n_actions`` discrete actions (Chae: no, weak, mid and strong
braking); the agent acts epsilon-greedily on it. A minibatch regresses Q(s, a) onto

    DQN:         y = r + gamma * (1 - terminated) * max_a' Q'(s', a')
    Double DQN:  y = r + gamma * (1 - terminated) * Q'(s', argmax_a' Q(s', a'))

where Q' is a target copy of Q refreshed every ``target_every`` updates. Taking the max of one noisy estimate
overestimates it; Double DQN lets the online network choose a' and the target network value it, so an action
whose value one network happens to overrate is not also valued by that same error.

**Trauma memory.** Collisions are rare, and they are terminal: the one transition that carries the collision
penalty is one among thousands in the replay memory, so uniform sampling replays it seldom, and one-step TD
needs it replayed many times before the penalty reaches the states that led to it. Chae keep a second, small
memory holding only collision transitions and draw ``trauma_batch`` of them into every minibatch; without it
their agent did not converge in over 2,000 episodes (their Fig. 5). Which transition is a trauma is the caller's
decision (``remember(..., trauma=True)``); every transition goes into the replay memory as well. With
``loss="sum"`` the loss is Chae's Eq. 9: the sum of squared TD errors over the replay batch plus the same sum
over the trauma batch.

Written in the spirit of CleanRL's ``dqn.py`` but as an importable module; unlike ``ddpg.DDPG`` the agent owns
its memories, because the trauma memory is part of the algorithm. A typical loop::

    agent = DQN(obs_dim, n_actions, DQNConfig(), seed=0)
    obs, _ = env.reset(seed=0)
    for step in range(total_steps):
        action = agent.act(obs, step)                      # epsilon-greedy, epsilon from the step
        next_obs, reward, terminated, truncated, info = env.step(action)
        agent.remember(obs, action, reward, next_obs, terminated, trauma=info["collision"])
        agent.update()                                     # None until warm-up is over
        obs = env.reset()[0] if terminated or truncated else next_obs

Store ``terminated`` (a true end: a crash, the hazard passed), not ``terminated or truncated``: a transition cut
by a time limit must still bootstrap from ``next_obs``.

Everything random after construction (exploration, minibatch indices) comes from one ``np.random.Generator``
whose state is part of ``state_dict()``, together with the memories, so a resumed run continues exactly where it
stopped.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..common import Checked, ConfigValueError, positive_fields
from .replay import CircularStore

OPTIMIZERS = ("rmsprop", "adam")
LOSSES = ("sum", "mse", "huber")


@dataclass
class DQNConfig(Checked):
    """The hyperparameters of DQN and Double DQN with Chae's trauma memory."""

    hidden: list[int] = field(default_factory=lambda: [100, 70, 50, 70, 100])
    """widths of the hidden layers (Chae: 100, 70, 50, 70, 100 between 15 inputs and 4 actions)"""
    leaky_slope: float = 0.01
    """negative slope of the leaky ReLU after every hidden layer (0 = plain ReLU)"""
    optimizer: str = "rmsprop"
    """the optimiser: rmsprop or adam"""
    lr: float = 5e-4
    """learning rate (the initial one when ``lr_final`` is set)"""
    lr_final: float | None = None
    """if set, the learning rate decays exponentially from ``lr`` to this over ``total_steps`` updates, then stays
    there (Merola et al.: 1e-4 to 1e-6). None = constant ``lr``"""
    total_steps: int = 100_000
    """updates over which ``lr`` decays to ``lr_final``. With one update per environment step after warm-up, set it
    to the run's length in steps"""
    gamma: float = 0.99
    """discount factor"""
    batch_size: int = 32
    """transitions drawn from the replay memory per update"""
    buffer_size: int = 10_000
    """replay memory capacity in transitions; the oldest is overwritten when it is full"""
    trauma_size: int = 1_000
    """trauma memory capacity in transitions"""
    trauma_batch: int = 10
    """trauma transitions added to every update's batch (fewer while the trauma memory holds fewer). 0 turns the
    trauma memory off: plain DQN"""
    trauma_lead: int = 0
    """the transitions up to this many steps before a trauma, in the same episode, enter the trauma memory with it
    (0: the trauma alone, as Chae et al.). The braking decision that would have prevented a bump comes a second or
    more before it; replaying those states with the trauma shortens the way the penalty travels back by TD"""
    target_every: int = 500
    """updates between hard copies of the online network into the target network"""
    target_average: int = 1
    """Averaged-DQN (Anschel et al. 2017): the TD target values the next state by the mean of the last this-many
    target networks (the copies made ``target_every`` updates apart), not by the latest alone. 1 = one target
    network, as DQN. Averaging K copies divides the variance that the target's approximation error adds to the
    targets by about K, which Anschel et al. show damps DQN's oscillations; for when successive checkpoints of a
    run swing between policies (Chae: bumping and needless stops, 250 episodes apart). Measured on Chae (K = 10,
    one seed): it swings as widely"""
    double: bool = False
    """Double DQN target: the online network chooses the next action, the target network values it"""
    advantage_alpha: float = 0.0
    """advantage learning (Bellemare et al. 2016, "Increasing the action gap"): the target of Q(s, a) is lowered by
    alpha * (max_b Q'(s, b) - Q'(s, a)), which keeps the greedy policy optimal but widens the gap between the best
    action and the others about 1 / (1 - alpha) times. 0 = the plain Bellman target. For when the values that
    separate actions are small beside the values' own range and the network's error (Chae: a collision costs
    100, a needless stop at 10 km/h 0.3)"""
    value_rescale: bool = False
    """learn h(Q) instead of Q, with h(x) = sign(x) (sqrt(|x| + 1) - 1) + 0.001 x (Pohlen et al. 2018, as in R2D2):
    the TD target becomes h(r + gamma h^-1(Q'(s', a'))). h is increasing, so the greedy action is the same, but it
    squeezes large values (a collision's -100 becomes about -9) while values near 0 keep a slope of 1/2: the
    network's error, which scales with the range it must fit, shrinks beside the small differences between
    actions. ``q_values`` answers in the reward's units either way. False = plain Q, as Chae et al. For when the
    decision turns on differences of tenths beside a penalty of 100 (Chae: at 10 km/h a needless stop costs 0.3)"""
    eps_start: float = 1.0
    """exploration probability at step 0"""
    eps_end: float = 0.05
    """exploration probability from ``eps_decay_steps`` on"""
    eps_decay_steps: int = 10_000
    """environment steps over which epsilon falls linearly from ``eps_start`` to ``eps_end``"""
    warmup_steps: int = 1000
    """transitions remembered before the first update, so early batches are not drawn from a few transitions"""
    loss: str = "sum"
    """how TD errors make the loss. "sum": Chae's Eq. 9, the sum of squared TD errors over the replay and the
    trauma batch; "mse": their mean; "huber": the mean Huber loss (delta 1), as in Mnih et al. 2015"""
    dueling: bool = False
    """the dueling head (Wang et al. 2016): the last hidden layer feeds a state value V(s) and advantages A(s, .),
    and Q = V + A - mean(A). The paper's network has one linear head (False). When the values that separate the
    actions are small beside the values themselves (Chae: waiting or braking gently at low speed differ by
    hundredths, beside a bump's 100), the advantages are learnt in their own stream"""
    trauma_weight_final: float | None = None
    """if set, the trauma batch's share of the loss is weighted by a factor that decays exponentially from 1 to
    this over ``total_steps`` updates (the schedule of ``lr_final``), then stays there. None = weight 1 throughout,
    as Chae et al. Every trauma transition also enters the replay memory, so the trauma batch over-samples
    collisions (Chae, late in a run: thousands of times their share of the replay memory): it makes the penalty
    travel back quickly while collisions are rare, but late in training it biases the fit towards the states near
    a collision (Chae: gentle braking for every pedestrian in case it starts); annealing its weight removes that
    bias as prioritised replay's importance weights do (Schaul et al. 2016)"""
    trauma_weight_hold: float = 0.0
    """with ``trauma_weight_final``: the share of ``total_steps`` updates during which the weight stays 1 before it
    starts to decay (then over the remaining updates). 0 = decay from the first update. For runs that have not yet
    learnt to avoid the collisions when the decay starts (Chae: the first bumps are avoided only when epsilon is
    low, around 55 % of the run), so that the bias is removed after the penalty has travelled back, not before"""
    normalize_obs: bool = False
    """standardise each observation feature by the mean and standard deviation of the replay memory at the first
    update (the warm-up transitions), frozen from then on and saved with the network. False = raw inputs, as
    Chae et al. (their state mixes metres up to ~80 with speeds). Measured on Chae (one seed): learning starts
    as late and the greedy agent swings as much as with raw inputs"""
    grad_clip: float | None = 10.0
    """clip the gradients' global norm to this before each step; None = no clipping. With ``loss="sum"`` the
    gradient grows with the batch, and one collision penalty can be large"""
    greedy_average: float | None = None
    """if set, a third copy of the network follows the online one as an exponential moving average of its weights
    (after every update, w_avg := d w_avg + (1 - d) w_online, d = this), and greedy decisions (``act(...,
    explore=False)``: evaluation, checkpoint selection) use it; exploration and the TD targets do not. None = greedy
    decisions use the online network, as Chae et al. For when successive checkpoints of one run act very
    differently (Chae: 250 episodes apart, 1 % and 30 % bumps), as weight averaging does in Polyak and Juditsky 1992
    and SWA (Izmailov et al. 2018): 1 - d is the inverse of the number of updates averaged over. Measured on Chae
    (d = 0.9999, three seeds): the same two runs in three pass the bars as without it"""

    def problems(self):
        yield from positive_fields(self, "lr", "total_steps", "batch_size", "buffer_size", "target_every")
        yield from positive_fields(self, "target_average")
        yield from positive_fields(self, "eps_decay_steps")
        if self.lr_final is not None and not 0 < self.lr_final <= self.lr:
            yield ConfigValueError("lr_final", self.lr_final, f"it must be in (0, lr={self.lr}] or null")
        if self.trauma_weight_final is not None and not 0 < self.trauma_weight_final <= 1:
            yield ConfigValueError("trauma_weight_final", self.trauma_weight_final, "it must be in (0, 1] or null")
        if not 0 <= self.trauma_weight_hold < 1:
            yield ConfigValueError("trauma_weight_hold", self.trauma_weight_hold, "it must be in [0, 1)")
        if self.grad_clip is not None and not self.grad_clip > 0:
            yield ConfigValueError("grad_clip", self.grad_clip, "it must be positive or null")
        if not 0 <= self.gamma <= 1:
            yield ConfigValueError("gamma", self.gamma, "it must be in [0, 1]")
        if self.greedy_average is not None and not 0 < self.greedy_average < 1:
            yield ConfigValueError("greedy_average", self.greedy_average, "it must be in (0, 1) or null")
        if not 0 <= self.advantage_alpha < 1:
            yield ConfigValueError("advantage_alpha", self.advantage_alpha, "it must be in [0, 1)")
        for key in ("eps_start", "eps_end"):
            if not 0 <= getattr(self, key) <= 1:
                yield ConfigValueError(key, getattr(self, key), "it must be in [0, 1]")
        if self.eps_end > self.eps_start:
            yield ConfigValueError("eps_end", self.eps_end, f"it must be at most eps_start={self.eps_start}")
        for key in ("trauma_size", "trauma_batch", "trauma_lead", "warmup_steps", "leaky_slope"):
            if getattr(self, key) < 0:
                yield ConfigValueError(key, getattr(self, key), "it must be >= 0")
        if self.trauma_batch > self.trauma_size:
            yield ConfigValueError(
                "trauma_batch", self.trauma_batch, f"it must be at most trauma_size={self.trauma_size}"
            )
        if self.batch_size > self.buffer_size:
            yield ConfigValueError("batch_size", self.batch_size, f"it must be at most buffer_size={self.buffer_size}")
        if self.optimizer not in OPTIMIZERS:
            yield ConfigValueError("optimizer", self.optimizer, f"it must be one of {', '.join(OPTIMIZERS)}")
        if self.loss not in LOSSES:
            yield ConfigValueError("loss", self.loss, f"it must be one of {', '.join(LOSSES)}")
        if not all(isinstance(w, int) and w > 0 for w in self.hidden):
            yield ConfigValueError("hidden", list(self.hidden), "layer widths must be positive integers")


RESCALE_EPS = 1e-3  # Pohlen et al. 2018's epsilon: h grows linearly far out, so h^-1 stays finite


def squash(x: torch.Tensor) -> torch.Tensor:
    """h(x) = sign(x) (sqrt(|x| + 1) - 1) + eps x (``DQNConfig.value_rescale``)."""
    return torch.sign(x) * (torch.sqrt(torch.abs(x) + 1.0) - 1.0) + RESCALE_EPS * x


def unsquash(y: torch.Tensor) -> torch.Tensor:
    """h^-1(y), in closed form (Pohlen et al. 2018, Proposition A.2)."""
    root = (torch.sqrt(1.0 + 4.0 * RESCALE_EPS * (torch.abs(y) + 1.0 + RESCALE_EPS)) - 1.0) / (2.0 * RESCALE_EPS)
    return torch.sign(y) * (root**2 - 1.0)


def td_loss(q: torch.Tensor, target: torch.Tensor, kind: str, batch: int | None = None) -> torch.Tensor:
    """The TD loss of ``kind`` ("sum", "mse", "huber"; see DQNConfig.loss); the means divide by ``batch``
    (default: len(q)), so that a batch split in parts sums back to the whole."""
    if kind == "sum":
        return ((q - target) ** 2).sum()
    if batch is None:  # torch's own mean, so runs at trauma weight 1 reproduce earlier ones bit for bit
        return F.mse_loss(q, target) if kind == "mse" else F.smooth_l1_loss(q, target)
    reduction = F.mse_loss if kind == "mse" else F.smooth_l1_loss
    return reduction(q, target, reduction="sum") / batch


class QNetwork(nn.Module):
    """Q(s, .): an MLP from the observation to one value per action, leaky ReLU between layers; with ``dueling``,
    a value and an advantage head on the last hidden layer, Q = V + A - mean(A)."""

    def __init__(
        self,
        obs_dim: int,
        n_actions: int,
        hidden: Sequence[int] = (100, 70, 50, 70, 100),
        leaky_slope: float = 0.01,
        dueling: bool = False,
        normalize: bool = False,
    ):
        super().__init__()
        self.normalize = bool(normalize)
        if self.normalize:  # set once by DQN.update (freeze_normalization); buffers, so checkpoints carry them
            self.register_buffer("obs_mean", torch.zeros(obs_dim))
            self.register_buffer("obs_std", torch.ones(obs_dim))
        layers: list[nn.Module] = []
        in_dim = obs_dim
        for width in hidden:
            layers += [nn.Linear(in_dim, width), nn.LeakyReLU(leaky_slope)]
            in_dim = width
        self.dueling = bool(dueling)
        if self.dueling:
            self.net = nn.Sequential(*layers)
            self.value, self.advantage = nn.Linear(in_dim, 1), nn.Linear(in_dim, n_actions)
        else:
            layers.append(nn.Linear(in_dim, n_actions))
            self.net = nn.Sequential(*layers)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Returns Q with shape (batch, n_actions)."""
        if self.normalize:
            obs = (obs - self.obs_mean) / self.obs_std
        if not self.dueling:
            return self.net(obs)
        h = self.net(obs)
        advantage = self.advantage(h)
        return self.value(h) + advantage - advantage.mean(dim=-1, keepdim=True)


class TransitionBuffer(CircularStore):
    """The replay or the trauma memory of discrete-action transitions."""

    FIELDS = ("obs", "actions", "rewards", "next_obs", "terminated")
    RESUME_HINT = "resume with the same buffer_size and trauma_size"

    def __init__(self, capacity: int, obs_dim: int):
        n = int(capacity)
        super().__init__(
            n,
            {
                "obs": np.zeros((n, obs_dim), dtype=np.float32),
                "actions": np.zeros(n, dtype=np.int64),  # int64: what torch's gather indexes with
                "rewards": np.zeros(n, dtype=np.float32),
                "next_obs": np.zeros((n, obs_dim), dtype=np.float32),
                "terminated": np.zeros(n, dtype=np.float32),
            },
        )

    def add(self, obs, action: int, reward: float, next_obs, terminated: bool) -> None:
        i = self.advance()
        self.obs[i], self.actions[i], self.rewards[i] = obs, action, reward
        self.next_obs[i], self.terminated[i] = next_obs, float(terminated)


class DQN:
    """Online and target Q-networks, their optimiser and learning-rate schedule, the replay and trauma memories,
    and the agent's own random generator."""

    def __init__(self, obs_dim: int, n_actions: int, cfg: DQNConfig, seed: int):
        self.obs_dim, self.n_actions, self.cfg = int(obs_dim), int(n_actions), cfg
        self.rng = np.random.default_rng(seed)
        self.steps = 0  # transitions remembered: the clock of epsilon and of warm-up
        self.updates = 0
        # Initialise from `seed` without consuming or resetting the global torch RNG, which the caller may use.
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            shape = (obs_dim, n_actions, cfg.hidden, cfg.leaky_slope, cfg.dueling, cfg.normalize_obs)
            self.q_network, self.target_network = QNetwork(*shape), QNetwork(*shape)
        self.target_network.load_state_dict(self.q_network.state_dict())
        self.target_network.requires_grad_(False)  # moved only by hard copies
        # target_average: the earlier copies, newest first; all start as the initial network, as the target does
        self.earlier_targets: list[QNetwork] = []
        for _ in range(cfg.target_average - 1):
            self.earlier_targets.append(QNetwork(*shape))
            self.earlier_targets[-1].load_state_dict(self.q_network.state_dict())
            self.earlier_targets[-1].requires_grad_(False)
        self.average_network = None  # greedy_average: the weight average that greedy decisions use
        if cfg.greedy_average is not None:
            self.average_network = QNetwork(*shape)
            self.average_network.load_state_dict(self.q_network.state_dict())
            self.average_network.requires_grad_(False)

        optimizer = {"rmsprop": torch.optim.RMSprop, "adam": torch.optim.Adam}[cfg.optimizer]
        self.optimizer = optimizer(self.q_network.parameters(), lr=cfg.lr)
        ratio = 1.0 if cfg.lr_final is None else cfg.lr_final / cfg.lr
        total = cfg.total_steps
        # lr * ratio^(u / total): exactly lr_final after `total` updates, held there after.
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, lambda u: ratio ** (min(u, total) / total))
        self.normalized = False  # whether the networks' input statistics are frozen yet (normalize_obs)

        self.replay = TransitionBuffer(cfg.buffer_size, obs_dim)
        self.trauma = TransitionBuffer(cfg.trauma_size, obs_dim) if cfg.trauma_batch > 0 else None
        self._lead: deque = deque(maxlen=cfg.trauma_lead)  # this episode's latest transitions, for trauma_lead

    # ------------------------------------------------------------------ acting
    def epsilon(self, step: int | None = None) -> float:
        """Exploration probability at environment step ``step`` (default: transitions remembered so far)."""
        step = self.steps if step is None else step
        frac = min(max(step, 0) / self.cfg.eps_decay_steps, 1.0)
        return self.cfg.eps_start + frac * (self.cfg.eps_end - self.cfg.eps_start)

    @torch.no_grad()
    def q_values(self, obs: np.ndarray, averaged: bool = False) -> np.ndarray:
        """Q(obs, .) from the online network (``averaged``: from the weight average when ``greedy_average`` keeps
        one), for one observation (n_actions,) or a batch (n, n_actions)."""
        net = self.average_network if averaged and self.average_network is not None else self.q_network
        values = net(torch.as_tensor(obs, dtype=torch.float32))
        return (unsquash(values) if self.cfg.value_rescale else values).numpy()

    def act(self, obs: np.ndarray, step: int | None = None, explore: bool = True) -> int:
        """A uniformly random action with probability ``epsilon(step)`` if ``explore``, else the greedy one: of the
        online network while exploring, of the weight average (``greedy_average``) when not."""
        if explore and self.rng.random() < self.epsilon(step):
            return int(self.rng.integers(self.n_actions))
        return int(np.argmax(self.q_values(obs, averaged=not explore)))

    def remember(
        self, obs, action: int, reward: float, next_obs, terminated: bool, trauma: bool = False, episode_end=None
    ) -> None:
        """Store a transition in the replay memory and, if ``trauma`` and the trauma memory is on, in that too
        (after the ``trauma_lead`` transitions before it). ``episode_end`` (default: ``terminated``) tells where an
        episode ends, so that a lead never reaches into the previous episode: pass ``terminated or truncated``."""
        transition = (obs, action, reward, next_obs, terminated)
        self.replay.add(*transition)
        if trauma and self.trauma is not None:
            for earlier in self._lead:
                self.trauma.add(*earlier)
            self.trauma.add(*transition)
            self._lead.clear()
        elif self.cfg.trauma_lead:
            self._lead.append(transition)
        if terminated if episode_end is None else episode_end:
            self._lead.clear()
        self.steps += 1

    # ------------------------------------------------------------------ learning
    def trauma_weight(self, update: int | None = None) -> float:
        """The trauma batch's loss weight at update ``update`` (default: updates so far): 1, decaying exponentially
        to ``trauma_weight_final`` over ``total_steps`` updates when that is set (after the first
        ``trauma_weight_hold`` share of them at 1)."""
        final = self.cfg.trauma_weight_final
        if final is None:
            return 1.0
        u = self.updates if update is None else update
        hold = self.cfg.trauma_weight_hold * self.cfg.total_steps
        progress = (min(u, self.cfg.total_steps) - hold) / (self.cfg.total_steps - hold)
        return float(final ** max(progress, 0.0))

    @torch.no_grad()
    def freeze_normalization(self) -> None:
        """Both networks standardise their inputs by the replay memory's per-feature mean and standard deviation
        (a feature that never varied keeps scale 1)."""
        obs = self.replay.obs[: len(self.replay)]
        mean = torch.as_tensor(obs.mean(axis=0), dtype=torch.float32)
        std = torch.as_tensor(obs.std(axis=0), dtype=torch.float32)
        std = torch.where(std > 1e-6, std, torch.ones_like(std))
        for net in (self.q_network, self.target_network, self.average_network, *self.earlier_targets):
            if net is None:
                continue
            net.obs_mean.copy_(mean)
            net.obs_std.copy_(std)
        self.normalized = True

    def target_values(self, obs: torch.Tensor) -> torch.Tensor:
        """Q'(obs, .): the target network's values, or with ``target_average`` > 1 the mean over the latest copies."""
        values = self.target_network(obs)
        if not self.earlier_targets:
            return values
        for net in self.earlier_targets:
            values = values + net(obs)
        return values / (1 + len(self.earlier_targets))

    @torch.no_grad()
    def td_targets(
        self, reward: torch.Tensor, next_obs: torch.Tensor, terminated: torch.Tensor, obs=None, action=None
    ) -> torch.Tensor:
        """y = r + gamma (1 - terminated) Q'(s', a'), a' = argmax Q'(s', .) (DQN) or argmax Q(s', .) (Double DQN)
        (with ``value_rescale``, y = h(r + gamma (1 - terminated) h^-1(Q'(s', a'))), the networks holding h(Q));
        with ``advantage_alpha`` > 0, minus alpha (max_b Q'(s, b) - Q'(s, a)), which needs ``obs`` and ``action``.
        Q' is ``target_values``: the mean of the latest ``target_average`` target copies."""
        reward = torch.as_tensor(reward, dtype=torch.float32)
        next_obs = torch.as_tensor(next_obs, dtype=torch.float32)
        terminated = torch.as_tensor(terminated, dtype=torch.float32)
        next_q = self.target_values(next_obs)
        if self.cfg.double:
            next_action = self.q_network(next_obs).argmax(dim=1, keepdim=True)
            next_value = next_q.gather(1, next_action).squeeze(1)
        else:
            next_value = next_q.max(dim=1).values
        if self.cfg.value_rescale:  # the networks hold h(Q): back to returns, one Bellman step, and squash again
            target = squash(reward + self.cfg.gamma * (1.0 - terminated) * unsquash(next_value))
        else:
            target = reward + self.cfg.gamma * (1.0 - terminated) * next_value
        if self.cfg.advantage_alpha > 0:
            if obs is None or action is None:
                raise ValueError("advantage learning (advantage_alpha > 0) needs the batch's obs and action")
            q_here = self.target_values(torch.as_tensor(obs, dtype=torch.float32))
            taken = q_here.gather(1, torch.as_tensor(action, dtype=torch.int64).view(-1, 1)).squeeze(1)
            target = target - self.cfg.advantage_alpha * (q_here.max(dim=1).values - taken)
        return target

    def update(self) -> dict[str, float] | None:
        """One gradient step on a replay batch plus a trauma batch; every ``target_every``-th also copies the
        online network into the target. None (and nothing changes) while warming up.

        Returns loss, q_mean (mean Q(s, a) over the batch), target_mean, trauma_in_batch, trauma_weight and lr (the
        rate this step used)."""
        cfg = self.cfg
        if self.steps < cfg.warmup_steps or len(self.replay) < cfg.batch_size:
            return None
        if cfg.normalize_obs and not self.normalized:
            self.freeze_normalization()
        batch = self.replay.sample(cfg.batch_size, self.rng)
        n_trauma = 0
        if self.trauma is not None and len(self.trauma) > 0:
            # Without replacement: while few collisions are stored, one of them is not replayed several times over.
            n_trauma = min(cfg.trauma_batch, len(self.trauma))
            trauma = self.trauma.sample(n_trauma, self.rng, replace=False)
            batch = {name: torch.cat([batch[name], trauma[name]]) for name in batch}

        target = self.td_targets(
            batch["rewards"], batch["next_obs"], batch["terminated"], batch["obs"], batch["actions"]
        )
        q = self.q_network(batch["obs"]).gather(1, batch["actions"].unsqueeze(1)).squeeze(1)
        weight = self.trauma_weight()
        if weight == 1.0:
            loss = td_loss(q, target, cfg.loss)
        else:  # the replay part and the down-weighted trauma part, each over the whole batch as above
            split = len(q) - n_trauma
            loss = td_loss(q[:split], target[:split], cfg.loss, len(q)) + weight * td_loss(
                q[split:], target[split:], cfg.loss, len(q)
            )

        lr = self.optimizer.param_groups[0]["lr"]
        self.optimizer.zero_grad()
        loss.backward()
        if cfg.grad_clip is not None:
            nn.utils.clip_grad_norm_(self.q_network.parameters(), cfg.grad_clip)
        self.optimizer.step()
        self.scheduler.step()
        self.updates += 1
        if self.average_network is not None:
            self._average()
        if self.updates % cfg.target_every == 0:
            self.sync_target()
        return {
            "loss": loss.item(),
            "q_mean": q.mean().item(),
            "target_mean": target.mean().item(),
            "trauma_in_batch": float(n_trauma),
            "trauma_weight": weight,
            "lr": float(lr),
        }

    @torch.no_grad()
    def _average(self) -> None:
        d = float(self.cfg.greedy_average)
        for avg, online in zip(self.average_network.parameters(), self.q_network.parameters(), strict=True):
            avg.mul_(d).add_(online, alpha=1.0 - d)

    def sync_target(self) -> None:
        """Target := online network; with ``target_average``, the previous target becomes the newest earlier copy
        and the oldest copy is dropped."""
        if self.earlier_targets:
            oldest = self.earlier_targets.pop()
            oldest.load_state_dict(self.target_network.state_dict())
            self.earlier_targets.insert(0, oldest)
        self.target_network.load_state_dict(self.q_network.state_dict())

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        return {
            "q_network": self.q_network.state_dict(),
            "target_network": self.target_network.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "rng": self.rng.bit_generator.state,
            "steps": self.steps,
            "updates": self.updates,
            "normalized": self.normalized,
            "replay": self.replay.state_dict(),
            "trauma": None if self.trauma is None else self.trauma.state_dict(),
            "average_network": None if self.average_network is None else self.average_network.state_dict(),
            "earlier_targets": [net.state_dict() for net in self.earlier_targets],
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        if (state["trauma"] is None) != (self.trauma is None):
            raise ValueError("the checkpoint and this agent disagree on whether the trauma memory is on (trauma_batch)")
        if (state.get("average_network") is None) != (self.average_network is None):
            raise ValueError(
                "the checkpoint and this agent disagree on whether greedy decisions use a weight average "
                "(greedy_average): resume or evaluate with the greedy_average the run was trained with"
            )
        earlier = state.get("earlier_targets", [])  # absent: saved before target_average existed
        if len(earlier) != len(self.earlier_targets):
            raise ValueError(
                f"the checkpoint averages {len(earlier) + 1} target networks and this agent "
                f"{len(self.earlier_targets) + 1} (target_average): resume or evaluate with the target_average the "
                "run was trained with"
            )
        self.q_network.load_state_dict(state["q_network"])
        self.target_network.load_state_dict(state["target_network"])
        for net, saved in zip(self.earlier_targets, earlier, strict=True):
            net.load_state_dict(saved)
        if self.average_network is not None:
            self.average_network.load_state_dict(state["average_network"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.rng.bit_generator.state = state["rng"]
        self.steps, self.updates = int(state["steps"]), int(state["updates"])
        self.normalized = bool(state.get("normalized", False))  # absent: saved before normalize_obs existed
        self.replay.load_state_dict(state["replay"])
        if self.trauma is not None:
            self.trauma.load_state_dict(state["trauma"])
