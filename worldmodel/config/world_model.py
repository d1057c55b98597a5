"""The world model's sections: the VAE and the LSTM."""

from __future__ import annotations

from dataclasses import dataclass

from envs.scene import NUM_CLASSES

from ..common import Checked, ConfigValueError
from ..common import positive_fields as _positive


@dataclass
class VAEConfig(Checked):
    """Phase 1: the World Models VAE on one-hot class maps (docs/design.md §5)."""

    latent_dim: int = 128
    # the first conv's channels, every later layer scaled with it; 32 is World Models' VAE (a 56 MB checkpoint with
    # its optimiser's state). The smoke scale's tests take 8 (4.5 MB)
    channels: int = 32
    num_classes: int = NUM_CLASSES
    lr: float = 1e-4
    batch_size: int = 32
    epochs: int = 2
    # loss weight per class = frequency ** -class_balance (0: plain summed CE, as World Models); 0.5 lifted
    # held-out Vehicles IoU from 0.17 to 0.50 at quick scale (docs/design.md §5)
    class_balance: float = 0.5
    free_bits: float = 0.0  # nats per latent dimension below which KL is not penalised (0 = off)
    kl_weight: float = 1.0

    @classmethod
    def as_recorded(cls, values: dict, settings: dict) -> None:
        if values.get("channels") == 32:
            values.pop("channels")  # World Models' VAE, as before the option
        super().as_recorded(values, settings)

    def problems(self):
        yield from _positive(self, "latent_dim", "channels", "batch_size", "epochs", "lr")
        if self.num_classes != NUM_CLASSES:
            yield ConfigValueError("num_classes", self.num_classes, f"the simulator renders {NUM_CLASSES} classes")
        if not 0.0 <= self.class_balance <= 1.0:
            yield ConfigValueError("class_balance", self.class_balance, "it must be in [0, 1]")
        for key in ("free_bits", "kl_weight"):
            if getattr(self, key) < 0:
                yield ConfigValueError(key, getattr(self, key), "it must be >= 0")


RNN_HEADS = ("mdn", "gaussian", "mse")


@dataclass
class RNNConfig(Checked):
    """Phase 2: the 512-unit LSTM over [z_t, a_t] predicting z_{t+1} (World Models MDN-RNN)."""

    hidden: int = 512
    head: str = "mdn"  # mdn | gaussian | mse
    gaussians: int = 5
    residual: bool = True  # predict z_{t+1} - z_t: an untrained model starts near persistence
    lr: float = 1e-4
    batch_size: int = 32
    epochs: int = 10
    seq_len: int = 32
    # false: the inputs are mu, as the agent feeds them (latent MSE 0.030 against 0.034 sampled, at quick scale);
    # true: resampled like the targets (World Models). Validation uses the same inputs as training
    sample_inputs: bool = False
    # steps of each window, from a random step on, that the LSTM also runs on its own predictions (as it dreams),
    # their NLL added with open_loop_weight; 0: one-step teacher forcing only, as World Models
    open_loop_steps: int = 0
    open_loop_weight: float = 1.0
    # measured after training (worldmodel/dreams.py): the action effect at this many held-out branch points over
    # effect_horizon steps, and open-loop quality on horizon_episodes held-out episodes; 0 skips a measurement
    effect_points: int = 40
    effect_horizon: int = 10
    horizon_episodes: int = 40

    UNHASHED = ("effect_points", "effect_horizon", "horizon_episodes")  # measured after training, not trained

    @classmethod
    def as_recorded(cls, values: dict, settings: dict) -> None:
        if not int(values.get("open_loop_steps", 0)):  # off: the model is trained as before the option
            values.pop("open_loop_steps", None)
            values.pop("open_loop_weight", None)
        super().as_recorded(values, settings)

    def problems(self):
        yield from _positive(self, "hidden", "batch_size", "epochs", "lr", "seq_len", "gaussians", "effect_horizon")
        if self.open_loop_steps < 0 or self.open_loop_steps >= self.seq_len:
            yield ConfigValueError(
                "open_loop_steps", self.open_loop_steps, f"it must be in [0, seq_len) = [0, {self.seq_len})"
            )
        if self.open_loop_weight < 0:
            yield ConfigValueError("open_loop_weight", self.open_loop_weight, "it must be >= 0")
        for key in ("effect_points", "horizon_episodes"):
            if getattr(self, key) < 0:
                yield ConfigValueError(key, getattr(self, key), "it must be >= 0 (0 skips the measurement)")
        if self.head not in RNN_HEADS:
            yield ConfigValueError("head", self.head, f"it must be one of {', '.join(RNN_HEADS)}")
