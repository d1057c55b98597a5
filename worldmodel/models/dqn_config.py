"""The DQN's hyperparameters (``DQNConfig``), apart from the learner so that reading a config never imports torch."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..common import Checked, ConfigValueError, positive_fields

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
    target_every: int = 500
    """updates between hard copies of the online network into the target network"""
    double: bool = False
    """Double DQN target: the online network chooses the next action, the target network values it"""
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
    trauma_weight_final: float | None = None
    """if set, the trauma batch's share of the loss is weighted by a factor that decays exponentially from 1 to
    this over ``total_steps`` updates (the schedule of ``lr_final``), then stays there. None = weight 1 throughout,
    as Chae et al. Every trauma transition also enters the replay memory, so the trauma batch over-samples
    collisions (Chae, late in a run: thousands of times their share of the replay memory): it makes the penalty
    travel back quickly while collisions are rare, but late in training it biases the fit towards the states near
    a collision (Chae: gentle braking for every pedestrian in case it starts); annealing its weight removes that
    bias as prioritised replay's importance weights do (Schaul et al. 2016)"""
    grad_clip: float | None = 10.0
    """clip the gradients' global norm to this before each step; None = no clipping. With ``loss="sum"`` the
    gradient grows with the batch, and one collision penalty can be large"""

    # how recorded runs hashed it (``Checked``): the options that leave the learner as before them, and a removed key
    ADDED_OFF = {"value_rescale": False, "trauma_weight_final": None}
    REMOVED = {"trauma_lead": 0}

    def problems(self):
        yield from positive_fields(self, "lr", "total_steps", "batch_size", "buffer_size", "target_every")
        yield from positive_fields(self, "eps_decay_steps")
        if self.lr_final is not None and not 0 < self.lr_final <= self.lr:
            yield ConfigValueError("lr_final", self.lr_final, f"it must be in (0, lr={self.lr}] or null")
        if self.trauma_weight_final is not None and not 0 < self.trauma_weight_final <= 1:
            yield ConfigValueError("trauma_weight_final", self.trauma_weight_final, "it must be in (0, 1] or null")
        if self.grad_clip is not None and not self.grad_clip > 0:
            yield ConfigValueError("grad_clip", self.grad_clip, "it must be positive or null")
        if not 0 <= self.gamma <= 1:
            yield ConfigValueError("gamma", self.gamma, "it must be in [0, 1]")
        for key in ("eps_start", "eps_end"):
            if not 0 <= getattr(self, key) <= 1:
                yield ConfigValueError(key, getattr(self, key), "it must be in [0, 1]")
        if self.eps_end > self.eps_start:
            yield ConfigValueError("eps_end", self.eps_end, f"it must be at most eps_start={self.eps_start}")
        for key in ("trauma_size", "trauma_batch", "warmup_steps", "leaky_slope"):
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
