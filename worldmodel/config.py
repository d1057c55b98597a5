"""The configuration: its schema (one dataclass per config section, registered in Hydra's ConfigStore), its
validation, and the two ways in (``compose`` for tests and notebooks, ``hydra_main`` for the stage commands).

The dataclasses are the single source of truth for every key, its type and its default (docs/design.md §9).
``conf/*.yaml`` only choose groups and override values (the ``scale`` presets, the ``reward`` choice), so a
misspelt key or a value of the wrong type stops Hydra at composition, naming the key. What a type cannot say
(a size must be positive, a share must lie in [0, 1]) is checked by one small ``problems()`` per dataclass, next to
its fields; ``validate(cfg)`` runs them all when a stage starts, and an impossible value stops the stage with
a ``StageError`` naming the key, before any work is done.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from dataclasses import dataclass, field, fields, is_dataclass

from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from envs.kim import CAR_LENGTH as KIM_CAR_LENGTH
from envs.scene import NUM_CLASSES

from .common import CONF_DIR, Checked, ConfigValueError, StageError, return_freed_memory
from .common import positive_fields as _positive
from .models.ddpg import DDPGConfig
from .models.dqn import DQNConfig


# ----------------------------------------------------------------------------- sections
@dataclass
class PathsConfig:
    data_root: str = "data"
    runs_root: str = "runs"
    data: str = "${paths.data_root}/${experiment}"
    runs: str = "${paths.runs_root}/${experiment}"
    # where evaluations on a test bank are recorded; empty: docs/results/ledger.csv of this repository
    ledger: str = ""


@dataclass
class AutopilotConfig(Checked):
    """The noisy lane-keeping autopilot that drives the data collection (``envs.NoisyAutopilot``)."""

    steer_noise: float = 0.15  # std of Gaussian noise on the steer channel
    throttle_noise: float = 0.15  # std of Gaussian noise on the throttle/brake channel
    excursion_rate: float = 0.03  # chance per step of starting a sustained brake, lane change or swerve
    excursion_s: list[float] = field(default_factory=lambda: [0.4, 1.5])  # duration range of an excursion
    onset_excursion_prob: float = 0.5  # chance of an excursion from the first step, where the hazards are
    hard_swerve_share: float = 0.2  # share of steering excursions that are constant hard swerves

    def problems(self):
        for key in ("steer_noise", "throttle_noise"):
            if getattr(self, key) < 0:
                yield ConfigValueError(f"autopilot.{key}", getattr(self, key), "a noise level must be >= 0")
        for key in ("excursion_rate", "onset_excursion_prob", "hard_swerve_share"):
            if not 0.0 <= getattr(self, key) <= 1.0:
                yield ConfigValueError(f"autopilot.{key}", getattr(self, key), "a probability must be in [0, 1]")
        lo_hi = list(self.excursion_s)
        if len(lo_hi) != 2 or not 0 < lo_hi[0] <= lo_hi[1]:
            yield ConfigValueError("autopilot.excursion_s", lo_hi, "it must be [shortest, longest] seconds, > 0")


@dataclass
class BranchConfig(Checked):
    """Counterfactual continuations in the collection (``worldmodel.recording``; data/README.md): in a share of the
    episodes the simulator is snapshotted at a random step and replayed under several constant actions, showing the
    same moment under different actions, which the autopilot alone rarely does."""

    share: float = 0.25  # share of recorded episodes that branch (each once); 0 records none
    actions: int = 4  # continuations per branch point, each one constant action drawn uniformly from [-1, 1]^2
    steps: int = 10  # steps per continuation (0.67 s), the horizon the dreams are judged at
    context: int = 8  # frames of the parent copied before the branch point, for the LSTM's warm-up
    latest_step: int = 20  # the branch point is drawn from steps 1 .. latest_step (the hazard is early)

    def problems(self):
        if not 0.0 <= self.share <= 1.0:
            yield ConfigValueError("branch.share", self.share, "it must be in [0, 1]")
        for key in ("actions", "steps", "latest_step"):
            if getattr(self, key) < 1:
                yield ConfigValueError(f"branch.{key}", getattr(self, key), "it must be >= 1")
        if self.context < 0:
            yield ConfigValueError("branch.context", self.context, "it must be >= 0")

    def settings(self) -> dict | None:
        """What the recorded data depends on; None when nothing branches."""
        if self.share <= 0:
            return None
        return {
            "share": float(self.share),
            "actions": int(self.actions),
            "steps": int(self.steps),
            "context": int(self.context),
            "latest_step": int(self.latest_step),
        }


@dataclass
class CollectConfig(Checked):
    """Phase 0 (``worldmodel.collect``)."""

    episodes: int = 120
    num_workers: int = 2
    episodes_per_shard: int = 16
    max_episode_s: float = 15.0  # the paper's 15 s sequences at 15 FPS
    validation_fraction: float = 0.1  # share of episodes held out, stored in split.json
    autopilot: AutopilotConfig = field(default_factory=AutopilotConfig)
    branch: BranchConfig = field(default_factory=BranchConfig)

    def problems(self):
        yield from _positive(self, "episodes", "num_workers", "episodes_per_shard", "max_episode_s")
        if not 0.0 <= self.validation_fraction < 1.0:
            yield ConfigValueError("validation_fraction", self.validation_fraction, "it must be in [0, 1)")


@dataclass
class FocusConfig(Checked):
    """The focus mix (``envs.sample_focus_scenario``): hazards at the speeds and TTCs where braking leaves
    injuries that a better manoeuvre avoids, plus no-hazard episodes where swerving only costs."""

    hazard_share: float = 0.85
    speed_range: list[float] = field(default_factory=lambda: [15.0, 30.0])
    ttc_range: list[float] = field(default_factory=lambda: [0.25, 1.1])

    def problems(self):
        if not 0.0 <= self.hazard_share <= 1.0:
            yield ConfigValueError("hazard_share", self.hazard_share, "it must be in [0, 1]")
        for key in ("speed_range", "ttc_range"):
            value = list(getattr(self, key))
            if len(value) != 2 or not 0 < value[0] <= value[1]:
                yield ConfigValueError(key, value, "it must be [low, high] with 0 < low <= high")

    def settings(self) -> dict:
        return {
            "version": 2,  # 2: the hazard state is stored beside the costs
            "hazard_share": float(self.hazard_share),
            "speed_range": list(map(float, self.speed_range)),
            "ttc_range": list(map(float, self.ttc_range)),
        }


@dataclass
class DemosConfig(Checked):
    """Planner demonstrations (``worldmodel.demonstrate``): the privileged planner drives the focus mix with the
    camera on, recorded in the rollout schema to ``data/NAME/demos/``. The agent never sees the true state: it
    learns from the frames, through the frozen world model."""

    episodes: int = 0  # 0 = no demonstrations (the paper's configuration)
    num_workers: int = 2
    episodes_per_shard: int = 25
    focus: FocusConfig = field(default_factory=FocusConfig)
    # the sides evaluate.oracle's planner may steer to (1 right, -1 left); one side removes the ambiguity that a
    # least-squares student averages into braking straight. Stored apart: data/NAME/demos_right/ for [1.0]
    teacher_sides: list[float] = field(default_factory=lambda: [1.0, -1.0])
    # s, the teacher's steering delays in place of evaluate.oracle.delays_s (null: those); [0.0] makes every DAgger
    # label say what to do now. Stored apart (data/NAME/demos_delays0/); no effect on family kim (docs/results/kim/)
    teacher_delays_s: list[float] | None = None

    def problems(self):
        yield from _positive(self, "num_workers", "episodes_per_shard")
        if self.teacher_delays_s is not None and (
            not self.teacher_delays_s or any(float(d) < 0 for d in self.teacher_delays_s)
        ):
            yield ConfigValueError(
                "teacher_delays_s", self.teacher_delays_s, "use delays >= 0 s, or null for evaluate.oracle's"
            )
        if self.episodes < 0:
            yield ConfigValueError("episodes", self.episodes, "it must be >= 0 (0 = no demonstrations)")
        sides = [float(x) for x in self.teacher_sides]
        if not sides or any(x not in (1.0, -1.0) for x in sides) or len(set(sides)) != len(sides):
            yield ConfigValueError("teacher_sides", sides, "use distinct values of 1.0 (right) and -1.0 (left)")

    def teacher_name(self) -> str:
        """'' for evaluate.oracle's planner steering both ways, else what differs, e.g. 'right', 'left_right',
        'delays0' or 'right_delays0-0.2' (names the store)."""
        sides = [float(x) for x in self.teacher_sides]
        parts = [] if sides == [1.0, -1.0] else ["right" if x > 0 else "left" for x in sides]
        if self.teacher_delays_s is not None:
            parts.append("delays" + "-".join(f"{float(d):g}" for d in self.teacher_delays_s))
        return "_".join(parts)


@dataclass
class EnvConfig(Checked):
    """Keyword arguments of ``envs.UrbanCollisionEnv`` (its docstring gives units and sources);
    ``common.make_env`` instantiates it."""

    _target_: str = "envs.UrbanCollisionEnv"
    camera: bool = True
    image_size: int = 64
    fov_deg: float = 90.0
    # degrees: a second camera at the same pose (obs "seg_tele") for agent.chooser.mask_camera=tele, where a
    # pedestrian 30 m ahead covers 10-20 px, against ~1 px at 90 degrees. null = none
    tele_fov_deg: float | None = None
    horizon_after_ttc_s: float | None = 3.0  # agent episodes: truncated this long after the sampled TTC
    mu: float = 1.0  # tyre-road friction coefficient (friction circle radius mu*g)
    occupants_per_car: int = 1
    step_s: float = 1.0 / 15.0  # seconds per step: the paper's 15 FPS (Chae, Kim and Merola step 0.1 s)
    family: str = "porav"  # the scenarios reset() samples: porav (the paper's) or chae (envs/chae.py)

    def problems(self):
        if self.image_size != 64:
            yield ConfigValueError("image_size", self.image_size, "the VAE's encoder takes 64x64 frames")
        yield from _positive(self, "mu", "occupants_per_car")
        if not 10.0 <= self.fov_deg <= 170.0:
            yield ConfigValueError("fov_deg", self.fov_deg, "the camera's field of view must be in [10, 170] degrees")
        if self.tele_fov_deg is not None and not 10.0 <= self.tele_fov_deg <= 170.0:
            yield ConfigValueError("tele_fov_deg", self.tele_fov_deg, "it must be in [10, 170] degrees, or null")
        if not 0.0 < self.step_s <= 0.5:
            yield ConfigValueError("step_s", self.step_s, "it must be in (0, 0.5] seconds")
        from envs.env import FAMILIES

        if self.family not in FAMILIES:
            yield ConfigValueError("family", self.family, f"it must be one of {', '.join(FAMILIES)}")
        if self.horizon_after_ttc_s is not None and self.horizon_after_ttc_s <= 0:
            yield ConfigValueError("horizon_after_ttc_s", self.horizon_after_ttc_s, "it must be > 0 (or null)")


@dataclass
class VAEConfig(Checked):
    """Phase 1: the World Models VAE on one-hot class maps (docs/design.md §5)."""

    latent_dim: int = 128
    num_classes: int = NUM_CLASSES
    lr: float = 1e-4
    batch_size: int = 32
    epochs: int = 2
    # loss weight per class = frequency ** -class_balance (0: plain summed CE, as World Models); 0.5 lifted
    # held-out Vehicles IoU from 0.17 to 0.50 at quick scale (docs/design.md §5)
    class_balance: float = 0.5
    free_bits: float = 0.0  # nats per latent dimension below which KL is not penalised (0 = off)
    kl_weight: float = 1.0

    def problems(self):
        yield from _positive(self, "latent_dim", "batch_size", "epochs", "lr")
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


MASK_CAMERAS = ("wide", "tele")


@dataclass
class ChooserConfig(Checked):
    """The chooser agent (``agent.learner=chooser``; ``envs/chooser.py``, ``worldmodel/chooser.py``): it brakes,
    and switches once to the candidate manoeuvre its scorer predicts to cost least. The scorer learns the exact
    costs of every candidate on straight-line braking's states, labelled by the simulator."""

    episodes: int = 3000  # labelled braking episodes (data/NAME/chooser_labels/), the last 15 % held out
    # the seed of the labelled scenarios; null: the training seed. Set, the seeds share one label set and differ
    # only in the scorer's initialisation and minibatches
    label_seed: int | None = None
    num_workers: int = 2
    # the labelled scenarios: hazards with this probability, at these speeds and TTCs (the bank's ranges)
    hazard_share: float = 0.85
    speed_range: list[float] = field(default_factory=lambda: [8.0, 30.0])
    ttc_range: list[float] = field(default_factory=lambda: [0.25, 1.5])
    # s: the chooser may switch only this early, then it keeps braking; with exact costs, 3 frames keep 89 % of the
    # planner's improvement, as much as 1.5 s does (docs/results/agent/)
    decide_s: float = 0.2
    # the candidates after straight-line braking: steer magnitudes x {held swerve, lane changes} x pedals x sides;
    # the exact chooser picks 0.3 s lane changes at steer 0.3 and 1.0 most, and 8 more candidates add 1 point
    steers: list[float] = field(default_factory=lambda: [0.3, 1.0])
    lane_change_s: list[float] = field(default_factory=lambda: [0.3])
    swerve: bool = False  # also held swerves
    pedals: list[float] = field(default_factory=lambda: [-1.0])
    sides: list[float] = field(default_factory=lambda: [1.0, -1.0])
    margin: float = 0.0  # switch only when the predicted saving over braking exceeds this (R2 units)
    # R2 units: switch only where braking itself is predicted to cost more than this: where braking is nearly safe
    # a switch has little to win and a wrong one much to lose. A decision-time rule: the scorer is fitted without it
    min_brake_cost: float = 0.0  # 0 = no floor
    # R2 units added to a candidate's labelled cost where it ends in a static object, so that the scorer keeps clear
    # of poles and walls (the bar on static collisions: 2 %); needs labels that record the flag (docs/results/agent/)
    static_penalty: float = 0.0
    hidden: list[int] = field(default_factory=lambda: [256, 256])
    dropout: float = 0.2
    lr: float = 1.0e-3
    weight_decay: float = 1.0e-4
    batch_size: int = 256
    steps: int = 6000  # minibatches; the scorer kept is the best on the held-out labelled episodes
    ensemble: int = 1  # the scorer is the mean of this many MLPs (each its own init and minibatches)
    # "cost": regress every candidate's cost; "advantage": braking's cost and the others' differences from it;
    # "policy": logits trained to minimise the expected cost of the softmax choice (cost-sensitive classification)
    target: str = "cost"
    # the scorer also reads, through a small CNN, a band of the raw frame around the horizon (envs.views.MaskView:
    # pedestrians and vehicles, this frame and the last): where the hazard is, not only its rows and columns
    mask_view: bool = False
    # which camera's band the scorer reads: "wide" (the world model's 90-degree camera, rows 20-44) or "tele"
    # (the narrow second camera of env.tele_fov_deg, rows 8-48, where the hazard pedestrian appears 20x larger)
    mask_camera: str = "wide"
    # the loss weight of a head on the scorer's first layer that guesses the privileged hazard state
    # (envs.chooser.hazard_state): learning by cheating for perception; the guess never acts. 0 = no head
    aux_weight: float = 0.0

    def problems(self):
        from envs.chooser import chooser_candidates

        yield from _positive(self, "episodes", "num_workers", "decide_s", "lr", "batch_size", "steps")
        if not 0.0 <= self.hazard_share <= 1.0:
            yield ConfigValueError("chooser.hazard_share", self.hazard_share, "it must be in [0, 1]")
        for key in ("speed_range", "ttc_range"):
            value = list(getattr(self, key))
            if len(value) != 2 or not 0 < value[0] <= value[1]:
                yield ConfigValueError(f"chooser.{key}", value, "it must be [low, high] with 0 < low <= high")
        if self.min_brake_cost < 0:
            yield ConfigValueError("chooser.min_brake_cost", self.min_brake_cost, "it must be >= 0 (R2 units)")
        if self.static_penalty < 0:
            yield ConfigValueError("chooser.static_penalty", self.static_penalty, "it must be >= 0 (R2 units)")
        if self.margin < 0 or not 0.0 <= self.dropout < 1.0 or self.weight_decay < 0:
            yield ConfigValueError("chooser.margin", self.margin, "margin and weight_decay >= 0, dropout in [0, 1)")
        if self.aux_weight < 0:
            yield ConfigValueError("chooser.aux_weight", self.aux_weight, "it must be >= 0")
        if self.mask_camera not in MASK_CAMERAS:
            yield ConfigValueError("chooser.mask_camera", self.mask_camera, f"it must be one of {MASK_CAMERAS}")
        if self.ensemble < 1:
            yield ConfigValueError("chooser.ensemble", self.ensemble, "it must be >= 1")
        if self.target not in ("cost", "advantage", "policy"):
            yield ConfigValueError("chooser.target", self.target, "it must be cost, advantage or policy")
        if not self.hidden or any(int(h) < 1 for h in self.hidden):
            yield ConfigValueError("chooser.hidden", list(self.hidden), "use a non-empty list of layer sizes >= 1")
        try:
            chooser_candidates(self.steers, self.lane_change_s, self.pedals, self.sides, self.swerve)
        except ValueError as err:
            yield ConfigValueError("chooser", "...", str(err))

    def candidates(self, step_s: float = 1.0 / 15.0):
        from envs.chooser import chooser_candidates

        return chooser_candidates(
            [float(x) for x in self.steers],
            [float(x) for x in self.lane_change_s],
            [float(x) for x in self.pedals],
            [float(x) for x in self.sides],
            bool(self.swerve),
            step_s=float(step_s),
        )

    def label_settings(self) -> dict:
        """What the labels depend on (the store is rebuilt when any of it changes)."""
        return {
            "version": 2,  # 2: the hazard state is stored beside the costs
            "hazard_share": float(self.hazard_share),
            "speed_range": [float(x) for x in self.speed_range],
            "ttc_range": [float(x) for x in self.ttc_range],
            "decide_s": float(self.decide_s),
            "candidates": [vars(m) for m in self.candidates()],
        }


LEARNERS = ("ddpg", "chooser", "dqn")
# what an agent sees: the world model's [z, zhat(, speed)] from the camera, or Chae's privileged 15-value
# pedestrian history (envs/chae.py); a DDPG or chooser agent always sees the world model
# LIDAR scans (Kim), or Merola's last 4 camera frames as frozen VAE means or ResNet-18 features
OBSERVATIONS = ("worldmodel", "pedestrian_history", "lidar", "frames_vae", "frames_resnet")


@dataclass
class SelectConfig(Checked):
    """Checkpoint selection for the dqn learner on family chae (``worldmodel/peers/chae.py``). Every ``every``
    episodes once ``start`` of the run has passed, the greedy agent drives a validation draw of Chae's trials
    (``trials`` Scenario-1 trials at each TTC of ``ttcs`` and as many Scenario-2 trials, seeded by ``seed``: never
    the evaluation's ``evaluate.chae.seed``), and ``best.pt`` keeps the checkpoint that, among those bumping in at
    most ``max_bump`` % at every TTC, stops needlessly least (else: the one that bumps least); evaluation loads it.
    Chae's two metrics, not the reward, choose it: the reward does not tell a needless stop from a pass at 10-30
    km/h, and successive checkpoints of one run differ there (docs/results/chae/)."""

    every: int = 250  # episodes between validations; 0 = off, evaluation loads last.pt
    start: float = 0.25  # the share of agent.episodes before the first validation
    seed: int = 99
    trials: int = 200
    ttcs: list[float] = field(default_factory=lambda: [1.5, 1.7, 1.9])
    max_bump: float = 1.0  # %, at each TTC
    max_stops: float = 5.0  # %, needless stops: with max_bump, the bars that rescoring's candidates are inside
    # keep every validated checkpoint as validated/episodeNNNNN.pt (2 MB each), to choose again on a larger draw
    # (rescore below, or experiments/chae_reselect.py) without retraining
    keep: bool = False
    # after the run, this many kept checkpoints inside both bars that bump least at ttcs[0] drive a larger draw
    # (seeded by ``rescore_seed``), and best.pt becomes the one with the most room under both bars; 0 = off
    rescore: int = 0
    rescore_seed: int = 98
    rescore_trials: int = 300  # Scenario-1 trials per TTC of the rescoring draw, and as many in Scenario 2
    # s, the TTCs the rescoring draw drives, weighed by their highest bump rate; null = ttcs[0] alone, whose choices
    # bumped at TTC 2.5-3.7 s instead (docs/results/chae/); dqn_chae adds 2.5-3.5 s
    rescore_ttcs: list[float] | None = None
    # if the rescored choice is not inside both bars, train ``extend`` more episodes (the scale's) and choose again,
    # at most ``extend_blocks`` times (the preset's; 0 = off): the runs swing to the end (docs/results/chae/)
    extend: int = 1000
    extend_blocks: int = 0

    def problems(self):
        yield from _positive(self, "trials")
        yield from _draw_problems(self, "seed", "select.")
        yield from _draw_problems(self, "rescore_seed", "select.")
        if self.seed < 0:
            yield ConfigValueError("select.seed", self.seed, "it must be >= 0")
        if self.every < 0:
            yield ConfigValueError("select.every", self.every, "it must be >= 0 episodes (0 = off)")
        if not 0.0 <= self.start <= 1.0:
            yield ConfigValueError("select.start", self.start, "it must be a share of the run, in [0, 1]")
        if not self.ttcs or any(not 0.0 < float(t) < 5.0 for t in self.ttcs):
            yield ConfigValueError("select.ttcs", list(self.ttcs), "use a non-empty list of TTCs in (0, 5) s")
        if not 0.0 <= self.max_bump <= 100.0:
            yield ConfigValueError("select.max_bump", self.max_bump, "it must be a rate in [0, 100] %")
        if not 0.0 <= self.max_stops <= 100.0:
            yield ConfigValueError("select.max_stops", self.max_stops, "it must be a rate in [0, 100] %")
        if self.rescore < 0:
            yield ConfigValueError("select.rescore", self.rescore, "it must be >= 0 checkpoints (0 = off)")
        if self.rescore and not self.keep:
            yield ConfigValueError(
                "select.rescore", self.rescore, "it reads the kept checkpoints back: set agent.select.keep=true too"
            )
        if self.rescore and self.rescore_seed == self.seed:
            yield ConfigValueError(
                "select.rescore_seed", self.rescore_seed, "it must differ from agent.select.seed (a new draw)"
            )
        yield from _positive(self, "rescore_trials")
        if self.extend < 0:
            yield ConfigValueError("select.extend", self.extend, "it must be >= 0 episodes per block (0 = off)")
        if self.extend_blocks < 0:
            yield ConfigValueError("select.extend_blocks", self.extend_blocks, "it must be >= 0 blocks")
        if self.extend and self.extend_blocks and not self.rescore:
            yield ConfigValueError(
                "select.extend",
                self.extend,
                "it trains on until the rescoring finds a member: set agent.select.rescore too",
            )
        if self.extend and self.extend_blocks and self.every and self.extend % self.every:
            yield ConfigValueError(
                "select.extend", self.extend, f"use a multiple of agent.select.every ({self.every}) episodes"
            )
        if self.rescore_ttcs is not None and (
            not self.rescore_ttcs or any(not 0.0 < float(t) < 5.0 for t in self.rescore_ttcs)
        ):
            yield ConfigValueError(
                "select.rescore_ttcs", list(self.rescore_ttcs), "use null or a non-empty list of TTCs in (0, 5) s"
            )


@dataclass
class AgentConfig(DDPGConfig):
    """Phase 3: DDPG's hyperparameters (``DDPGConfig``, documented there) and the training loop's settings."""

    # names the run (runs/NAME/agent_r2_<variant>/seed0/): set by each preset in conf/agent/ to its file name
    variant: str = "ddpg"
    total_steps: int = 20000
    use_speed: bool = False  # append ego speed to the agent input
    # append where pedestrians and vehicles are in the current and previous raw frame (envs/views.py): what the
    # camera sees and the VAE loses, a 1-2 px pedestrian at 30 m/s
    frame_view: bool = False
    checkpoint_every: int = 2000
    # what the actor's output means (worldmodel/action_map.py): "none" | "brake" (the pedal is a residual on full
    # braking, so u = 0 is straight-line braking), and "wheel" | "grip" (steer as a share of mu g at this speed)
    anchor: str = "none"
    steer: str = "wheel"
    # training episodes: this share from the focus mix (demos.focus), the rest from the paper's distributions
    focus_share: float = 0.0
    # planner demonstrations (needs demos.episodes > 0 and `python -m worldmodel.demonstrate`): this share of every
    # minibatch comes from them (DDPGfD), and the actor is first cloned on them for bc_pretrain_steps minibatches
    demo_share: float = 0.0
    bc_pretrain_steps: int = 0
    # DAgger rounds after the first cloning: the student drives dagger_episodes focus-mix episodes, the planner
    # labels every state it reaches, and the actor is cloned again on everything so far
    dagger_rounds: int = 0
    dagger_episodes: int = 100
    # Kim's LIDAR agent: the cloning loss's weight on labels that steer (|steering| > 0.15 of full); 1 = plain least
    # squares. The planner steers on ~6 % of its labels, and a least-squares student under-steers (docs/results/kim/)
    bc_steer_weight: float = 1.0
    reward_scale: float = 1.0  # rewards are multiplied by this in the replay (the optimum does not change)
    # the rewards the pipeline trains this preset with (`agents:`); a student that only clones the R2 planner
    # lists r2 alone, since its R1 run would be the same network under another name
    rewards: list[str] = field(default_factory=lambda: ["r1", "r2"])
    # "ddpg" (the paper's learner, with the options above) or "chooser" (agent.chooser: costs of manoeuvres learnt
    # from the simulator's labels; R2 only, and none of the DDPG keys apply)
    learner: str = "ddpg"
    chooser: ChooserConfig = field(default_factory=ChooserConfig)
    # learner "dqn" (worldmodel/peers/chae.py): DQN / Double DQN with a trauma memory over discrete brake levels
    dqn: DQNConfig = field(default_factory=DQNConfig)
    episodes: int = 6000  # the dqn learner's training episodes (family chae: ~40 steps each)
    select: SelectConfig = field(default_factory=SelectConfig)  # the dqn learner on family chae: best.pt
    # the training steps of a LIDAR ddpg peer (Kim et al.: 100k) and of ddqn_merola (Merola et al.: 360k): a key of
    # its own, so that a scale can shrink it while the peer's preset keeps the paper's other settings
    peer_total_steps: int = 100_000
    # m: family kim's training draws the runner's crossing uniformly within this of the ego's middle (envs.kim.sample;
    # the paper does not say); 0 = the middle. Evaluate with the same evaluate.kim.impact_offset_spread
    kim_impact_offset_spread: float = 0.0
    # s, family chae's training TTCs, U(lo, hi); evaluation keeps its own. The paper's 1.5-4 s; dqn_chae trains
    # from 1.3 s, so that TTC 1.5 s, the bar's edge, is not training's edge (docs/results/chae/)
    chae_ttc_range: list[float] = field(default_factory=lambda: [1.5, 4.0])
    # m, std of the noise on the pedestrian's position in Chae's state (the paper: "slight"); a checkpoint records
    # it. 0.1 keeps older runs current; dqn_chae sets 0.05, where Chae's Table I points (docs/results/chae/)
    chae_noise_m: float = 0.1
    # share of agent.episodes over which the training noise rises from 0 to chae_noise_m (validation uses the full
    # noise); 0 = no curriculum. Keep it <= agent.select.start. Built, never trained (docs/results/chae/)
    chae_noise_ramp: float = 0.0
    # what the agent sees (OBSERVATIONS; choose with obs=NAME); paper_obs is what its preset's paper gives it: runs
    # with another observation get the suffix -NAME (agent_chae_dqn_chae-worldmodel/seed0)
    obs: str = "worldmodel"
    paper_obs: str = "worldmodel"
    # obs=frames_resnet: a local ResNet-18 state dict with torchvision's names (ImageNet weights cannot be
    # downloaded here; worldmodel/models/resnet.py refuses to run without them)
    resnet_weights: str | None = None

    def problems(self):
        from .action_map import ANCHORS, STEERS

        if self.learner not in LEARNERS:
            yield ConfigValueError("learner", self.learner, f"it must be one of {', '.join(LEARNERS)}")

        yield from super().problems()
        yield from _positive(self, "checkpoint_every", "reward_scale", "episodes")
        clones = self.learner == "ddpg" and self.bc_pretrain_steps > 0  # 0 steps: the cloned actor alone
        for key, applies in (("total_steps", self.learner == "ddpg"), ("peer_total_steps", True)):
            steps = getattr(self, key)
            if applies and (steps < 0 or (steps == 0 and not clones)):
                yield ConfigValueError(key, steps, "it must be > 0 (or 0 with a ddpg learner's bc_pretrain_steps > 0)")
        if not self.variant.replace("_", "").isalnum() or not self.variant.islower():
            yield ConfigValueError("variant", self.variant, "it must be a lower-case name of letters, digits and _")
        for key in ("obs", "paper_obs"):
            if getattr(self, key) not in OBSERVATIONS:
                yield ConfigValueError(key, getattr(self, key), f"it must be one of {', '.join(OBSERVATIONS)}")
        seen_by = {
            "ddpg": ("worldmodel", "lidar"),
            "chooser": ("worldmodel",),
            "dqn": ("worldmodel", "pedestrian_history", "frames_vae", "frames_resnet"),
        }
        if self.learner in seen_by and self.obs not in seen_by[self.learner]:
            yield ConfigValueError(
                "obs", self.obs, f"the {self.learner} learner sees one of: {', '.join(seen_by[self.learner])}"
            )
        for key in ("focus_share", "demo_share"):
            if not 0.0 <= getattr(self, key) <= 1.0:
                yield ConfigValueError(key, getattr(self, key), "it must be in [0, 1]")
        if not 0.0 <= self.kim_impact_offset_spread <= KIM_CAR_LENGTH / 2:
            yield ConfigValueError(
                "kim_impact_offset_spread",
                self.kim_impact_offset_spread,
                f"it must be in [0, {KIM_CAR_LENGTH / 2:g}] m (half the ego)",
            )
        ttcs = [float(t) for t in self.chae_ttc_range]
        if len(ttcs) != 2 or not 0.0 < ttcs[0] < ttcs[1] <= 5.0:
            yield ConfigValueError(
                "chae_ttc_range",
                list(self.chae_ttc_range),
                "use [lo, hi] with 0 < lo < hi <= 5 s (beyond 5 s the trigger would lie behind the ego)",
            )
        if not 0.0 <= self.chae_noise_m <= 1.0:
            yield ConfigValueError(
                "chae_noise_m", self.chae_noise_m, "it must be in [0, 1] m (0: the exact relative position)"
            )
        if not 0.0 <= self.chae_noise_ramp < 1.0:
            yield ConfigValueError(
                "chae_noise_ramp", self.chae_noise_ramp, "it must be in [0, 1): a fraction of agent.episodes"
            )
        elif self.chae_noise_ramp > 0 and self.obs != "pedestrian_history":
            yield ConfigValueError(
                "chae_noise_ramp",
                self.chae_noise_ramp,
                "only Chae's state (obs=pedestrian_history) has a noise to ramp",
            )
        if self.dagger_rounds < 0 or self.dagger_episodes < 1:
            yield ConfigValueError("dagger_rounds", self.dagger_rounds, "rounds must be >= 0, dagger_episodes >= 1")
        if self.bc_steer_weight <= 0 or (self.bc_steer_weight != 1.0 and self.obs != "lidar"):
            yield ConfigValueError(
                "bc_steer_weight",
                self.bc_steer_weight,
                "it must be > 0, and 1 unless the agent sees the LIDAR (obs=lidar)",
            )
        if self.dagger_rounds and not self.bc_pretrain_steps:
            yield ConfigValueError("dagger_rounds", self.dagger_rounds, "DAgger clones: set bc_pretrain_steps > 0")
        if self.bc_pretrain_steps < 0:
            yield ConfigValueError("bc_pretrain_steps", self.bc_pretrain_steps, "it must be >= 0")
        from envs.rewards import REWARDS

        if not self.rewards or any(r not in REWARDS for r in self.rewards):
            yield ConfigValueError("rewards", list(self.rewards), f"use a non-empty list of {', '.join(REWARDS)}")
        if self.anchor not in ANCHORS:
            yield ConfigValueError("anchor", self.anchor, f"it must be one of {', '.join(ANCHORS)}")
        if self.steer not in STEERS:
            yield ConfigValueError("steer", self.steer, f"it must be one of {', '.join(STEERS)}")


@dataclass
class RewardConfig(Checked):
    """R1 = -(n_ped + n_occ) (paper Eq. 7) or R2 = -(sum P_ped + sum P_occ) (Eq. 8); ``envs.rewards``."""

    name: str = "r2"

    def problems(self):
        from envs.rewards import REWARDS

        if self.name not in REWARDS:
            yield ConfigValueError("name", self.name, f"use one of {', '.join('reward=' + r for r in REWARDS)}")


@dataclass
class OracleConfig(Checked):
    """The privileged planner (``envs/planner.py``): the ceiling the agents are judged against."""

    replan_every_s: float = 0.2  # re-simulate the candidates from the true state this often
    pedals: list[float] = field(default_factory=lambda: [-1.0, -0.5, 0.0, 1.0])  # held pedal levels; must hold -1
    steers: list[float] = field(default_factory=lambda: [0.3, 0.6, 1.0])  # steering magnitudes, both ways
    delays_s: list[float] = field(default_factory=lambda: [0.0, 0.2, 0.4])  # when the steering starts
    lane_change_s: list[float] = field(default_factory=lambda: [0.3, 0.6])  # steer-then-counter-steer lengths
    # steering directions tried, in order: 1 right, -1 left (one side: a teacher without left/right ambiguity)
    sides: list[float] = field(default_factory=lambda: [1.0, -1.0])
    # frames of straight-line braking before planning starts: the perception ceiling (a camera policy that needs
    # this many frames to see the hazard); 0 for the ceiling itself
    brake_first: int = 0

    def problems(self):
        from envs.planner import candidate_manoeuvres

        if self.replan_every_s <= 0:
            yield ConfigValueError("oracle.replan_every_s", self.replan_every_s, "it must be > 0")
        if self.brake_first < 0:
            yield ConfigValueError("oracle.brake_first", self.brake_first, "it must be >= 0 frames")
        try:
            candidate_manoeuvres(
                pedals=list(self.pedals),
                steers=list(self.steers),
                delays_s=list(self.delays_s),
                lane_change_s=list(self.lane_change_s),
                sides=list(self.sides),
            )
        except ValueError as err:
            yield ConfigValueError("oracle", "...", str(err))


def agent_preset(cfg, name: str):
    """The ``agent`` section as ``train_agent experiment=... agent=<name>`` would compose it: the schema's defaults,
    then the scale's ``agent`` keys, then the preset ``conf/agent/<name>.yaml`` (the order of base.yaml's defaults).
    The preset the config was composed with keeps its command-line overrides."""
    if str(cfg.agent.variant) == name:
        return cfg.agent
    path = CONF_DIR / "agent" / f"{name}.yaml"
    if not path.exists():
        raise StageError(f"agent variant {name!r} has no preset {path}: restore it, or move its runs aside")
    preset = _load_preset(name)
    if _global_preset(path):
        preset = preset.get("agent", OmegaConf.create())
    scale = OmegaConf.create()
    if cfg.get("scale_name"):
        scale = OmegaConf.load(CONF_DIR / "scale" / f"{cfg.scale_name}.yaml").get("agent", OmegaConf.create())
    return OmegaConf.merge(OmegaConf.structured(AgentConfig), scale, preset)


def _global_preset(path) -> bool:
    return path.read_text().lstrip().startswith("# @package _global_")


def _load_preset(name: str):
    """A preset file with the presets its ``defaults`` list names merged under it: ``NAME`` (same group, same
    package) or ``/agent/NAME@agent`` (an agent preset placed under a global preset's ``agent`` key)."""
    preset = OmegaConf.load(CONF_DIR / "agent" / f"{name}.yaml")
    parents = []
    for entry in preset.pop("defaults", []):
        if not isinstance(entry, str) or entry == "_self_":
            continue
        if entry.startswith("/agent/"):
            parent, _, package = entry.removeprefix("/agent/").partition("@")
            parents.append(OmegaConf.create({package: _load_preset(parent)}) if package else _load_preset(parent))
        else:
            parents.append(_load_preset(entry))
    return OmegaConf.merge(*parents, preset) if parents else preset


def preset_globals(name: str) -> dict:
    """What an agent preset sets outside ``agent`` (a peer's preset, ``# @package _global_``, also picks its
    scenario family, step and reward: conf/agent/dqn_chae.yaml)."""
    path = CONF_DIR / "agent" / f"{name}.yaml"
    if not path.exists() or not _global_preset(path):
        return {}
    preset = OmegaConf.to_container(_load_preset(name))
    return {k: v for k, v in preset.items() if k not in ("agent", "defaults")}


def oracle_settings(cfg) -> dict:
    """``evaluate.oracle`` as plain keyword arguments of ``PrivilegedPlanner.from_settings``."""
    o = cfg.evaluate.oracle
    settings = {
        "replan_every_s": float(o.replan_every_s),
        "brake_first": int(o.brake_first),
        "pedals": [float(x) for x in o.pedals],
        "steers": [float(x) for x in o.steers],
        "delays_s": [float(x) for x in o.delays_s],
        "lane_change_s": [float(x) for x in o.lane_change_s],
    }
    sides = [float(x) for x in o.sides]
    if sides != [1.0, -1.0]:  # absent = both sides, so records made before the option still match
        settings["sides"] = sides
    step_s = float(cfg.env.step_s)
    if step_s != 1.0 / 15.0:  # absent = the default step, for the same reason
        settings["step_s"] = step_s
    return settings


def teacher_settings(cfg) -> dict:
    """The planner that records demonstrations and labels DAgger states: ``evaluate.oracle`` planning from the first
    frame, steering to ``demos.teacher_sides`` after ``demos.teacher_delays_s`` (``PrivilegedPlanner.from_settings``
    keyword arguments)."""
    settings = {k: v for k, v in oracle_settings(cfg).items() if k not in ("brake_first", "sides")}
    sides = [float(x) for x in cfg.demos.teacher_sides]
    if sides != [1.0, -1.0]:  # absent = both sides, so records made before the option still match
        settings["sides"] = sides
    delays = cfg.demos.get("teacher_delays_s")
    if delays is not None:
        settings["delays_s"] = [float(x) for x in delays]
    return settings


# braking (the floor), the privileged planner (the ceiling), and the planner after braking straight for its first 1
# or 2 frames: the perception ceilings of a camera policy that needs that many frames to see the hazard
SCRIPTED_POLICIES = ("braking", "oracle", "oracle_brake1", "oracle_brake2")
# family chae's scripted policies, in the order their rows are written (worldmodel/peers/chae.py SCRIPTED)
CHAE_SCRIPTED_POLICIES = ("braking", "ttc_braking", "latest_safe_braking", "closing_braking")


def _draw_problems(section, key: str, prefix: str = ""):
    """A validation draw may not be a sealed test seed (worldmodel/banks.py); ``prefix`` names the section."""
    from .banks import sealed_seed_problem

    why = sealed_seed_problem(getattr(section, key))
    if why:
        yield ConfigValueError(prefix + key, getattr(section, key), why)


@dataclass
class ChaeEvalConfig(Checked):
    """Chae et al.'s evaluation on family chae (worldmodel/peers/chae.py): Table I's bump rate per TTC, Scenario 2's
    unnecessary stops, stopping distances, and contact, impact speed and injury."""

    trials: int = 200  # seeded Scenario-1 trials per TTC (the paper: 10,000), and Scenario-2 trials
    ttcs: list[float] = field(default_factory=lambda: [round(0.9 + 0.2 * i, 1) for i in range(16)])  # 0.9 .. 3.9
    seed: int = 2017  # the validation draw (evaluate.bank=validation); the test draw is worldmodel/banks.py's
    # k >= 2: also evaluate ensembles of k consecutive seeds, greedy on their mean Q, which damps the runs' swings
    # (0: runs alone); 3: two ensembles in three inside both bars, single runs three in nine (docs/results/chae/)
    ensemble: int = 3
    # n > ensemble: each ensemble is the `ensemble` of n consecutive seeds that scored best on the selection draw;
    # 0 = `ensemble` consecutive seeds. Best three of five did no better (docs/results/chae/)
    ensemble_pool: int = 0
    # true: ensembles act by majority vote of their members' greedy levels (a tie: the highest mean Q), not on the
    # mean of Q; on nine seeds it was inside both bars as often as the mean (docs/results/chae/)
    ensemble_vote: bool = False
    # false: only the ensembles drive the trials (their members still load), for a large draw such as Table I's
    # 1,000 trials per TTC, where each run alone would cost as much again per seed
    singles: bool = True
    # scripted policies beside every dqn agent (CHAE_SCRIPTED_POLICIES; peers.chae.SCRIPTED builds them). Fewer for
    # a large draw whose scripted rows are already known: they are deterministic, the same trials give the same rows
    policies: list[str] = field(default_factory=lambda: list(CHAE_SCRIPTED_POLICIES))

    def problems(self):
        yield from _positive(self, "trials")
        yield from _draw_problems(self, "seed", "chae.")
        if not self.singles and not self.ensemble:
            yield ConfigValueError(
                "chae.singles", self.singles, "with no ensembles (chae.ensemble=0) no agent would drive"
            )
        if not self.ttcs or any(t <= 0 for t in self.ttcs):
            yield ConfigValueError("ttcs", list(self.ttcs), "give positive TTCs in seconds")
        if any(p not in CHAE_SCRIPTED_POLICIES for p in self.policies):
            yield ConfigValueError(
                "chae.policies", list(self.policies), f"use some of {', '.join(CHAE_SCRIPTED_POLICIES)}"
            )
        if self.ensemble == 1 or self.ensemble < 0:
            yield ConfigValueError("chae.ensemble", self.ensemble, "give 0 (none) or the members per ensemble, >= 2")
        if self.ensemble_vote and not self.ensemble:
            yield ConfigValueError(
                "chae.ensemble_vote", self.ensemble_vote, "a vote needs ensembles: set chae.ensemble"
            )
        if self.ensemble_pool and (self.ensemble < 2 or self.ensemble_pool <= self.ensemble):
            yield ConfigValueError(
                "chae.ensemble_pool",
                self.ensemble_pool,
                f"give 0 (consecutive seeds) or more runs than chae.ensemble={self.ensemble} members to choose from",
            )


@dataclass
class KimEvalConfig(Checked):
    """Kim et al.'s evaluation on family kim (worldmodel/peers/kim.py): Table 2's avoidance and injury per
    scenario, on the paper's 30 trials per scenario and on ``trials`` with 95 % intervals, and pairwise tests."""

    trials: int = 200  # seeded trials per scenario; the first 30 are the paper-sized table
    paper_trials: int = 30
    # scripted policies beside every LIDAR agent: straight-line braking, Kim's AEB-3m, the planner (the ceiling)
    policies: list[str] = field(default_factory=lambda: ["braking", "aeb3m", "oracle"])
    world_model_agents: bool = True  # also the paper's street-trained R1 / R2 agents and the chooser, as they are
    seed: int = 2020  # the validation draw (evaluate.bank=validation); the test draw is worldmodel/banks.py's
    # m forward of the ego's centre where the runner's path crosses it (envs.kim.KimSpec.impact_offset): 0 the middle
    # (training's), +2.25 the front bumper, -2.25 the rear; the paper does not say
    impact_offset: float = 0.0
    # > 0: each trial's crossing is drawn uniformly within impact_offset ± this (kept on the ego), from a stream of
    # its own, so the trials are otherwise the same; 2.25 with offset 0 = anywhere along the ego
    impact_offset_spread: float = 0.0

    def problems(self):
        yield from _positive(self, "trials", "paper_trials")
        yield from _draw_problems(self, "seed", "kim.")
        if not 0.0 <= self.impact_offset_spread <= 4.5:
            yield ConfigValueError("kim.impact_offset_spread", self.impact_offset_spread, "it must be in [0, 4.5] m")
        known = ("braking", "aeb3m", "oracle")
        if any(p not in known for p in self.policies):
            yield ConfigValueError("policies", list(self.policies), f"use some of {', '.join(known)}")
        half = KIM_CAR_LENGTH / 2
        if not abs(self.impact_offset) <= half:
            yield ConfigValueError("kim.impact_offset", self.impact_offset, f"it must be within ±{half:g} m")


@dataclass
class MerolaEvalConfig(Checked):
    """Merola et al.'s scenarios (worldmodel/peers/merola.py): collision rate, ego delta-v, injury risk and return
    per scenario for braking, the planner, the paper's world-model agents and every ddqn_merola agent."""

    trials: int = 100  # seeded trials per scenario, the same for every policy
    # straight-line braking from the start, Kim's AEB-3m (brakes once a footprint is within 3 m ahead), the planner
    policies: list[str] = field(default_factory=lambda: ["braking", "aeb3m", "oracle"])
    world_model_agents: bool = True  # also the paper's R1 / R2 agents and the chooser, at their own 1/15 s steps
    seed: int = 2022  # the validation draw (evaluate.bank=validation); the test draw is worldmodel/banks.py's

    def problems(self):
        yield from _positive(self, "trials")
        yield from _draw_problems(self, "seed", "merola.")
        if any(p not in ("braking", "aeb3m", "oracle") for p in self.policies):
            yield ConfigValueError("policies", list(self.policies), "use some of braking, aeb3m, oracle")


@dataclass
class EvaluateConfig(Checked):
    """The seeded scenario banks (docs/design.md §6) and the scripted policies evaluated beside the agents."""

    per_cell: int = 5
    ttcs: list[float] = field(default_factory=lambda: [0.5, 0.75, 0.9, 1.0, 1.1, 1.3, 1.5])
    speeds: list[float] = field(default_factory=lambda: [10.0, 20.0, 30.0])
    hazards: list[str] = field(default_factory=lambda: ["pedestrian", "car", "both"])
    # which bank (worldmodel/banks.py): "validation", drawn from validation_seed, for choosing settings and
    # checkpoints, as often as needed; "test", the sealed test bank, for final numbers only: each evaluation on it
    # is recorded in the ledger (paths.ledger) and goes to runs/NAME/eval_test/
    bank: str = "validation"
    validation_seed: int = 4711  # the default validation bank (runs/NAME/eval/); others go to eval_seed<N>/
    num_workers: int = 2  # processes; results are identical to 1
    # scripted policies; every agent under runs/${experiment}/agent_*/seed*/ is added
    policies: list[str] = field(default_factory=lambda: ["braking", "oracle"])
    oracle: OracleConfig = field(default_factory=OracleConfig)
    # which scenario family to evaluate: porav (the test bank above), chae, kim or merola (evaluate.<family>)
    family: str = "porav"
    chae: ChaeEvalConfig = field(default_factory=ChaeEvalConfig)
    kim: KimEvalConfig = field(default_factory=KimEvalConfig)
    merola: MerolaEvalConfig = field(default_factory=MerolaEvalConfig)

    def problems(self):
        yield from _positive(self, "per_cell", "num_workers")
        for key in ("ttcs", "speeds", "hazards"):
            if not getattr(self, key):
                yield ConfigValueError(key, [], "it must not be empty")
        for key in ("ttcs", "speeds"):
            if any(v <= 0 for v in getattr(self, key)):
                yield ConfigValueError(key, list(getattr(self, key)), "every value must be positive")
        from .banks import BANKS

        if self.bank not in BANKS:
            yield ConfigValueError("bank", self.bank, f"it must be one of {', '.join(BANKS)}")
        from envs.env import FAMILIES

        if self.family not in FAMILIES:
            yield ConfigValueError("family", self.family, f"it must be one of {', '.join(FAMILIES)}")
        yield from _draw_problems(self, "validation_seed")
        unknown = [h for h in self.hazards if h not in ("pedestrian", "car", "both")]
        if unknown:
            yield ConfigValueError("hazards", list(self.hazards), "hazards are pedestrian, car and both")
        if "braking" not in self.policies or any(p not in SCRIPTED_POLICIES for p in self.policies):
            yield ConfigValueError(
                "policies",
                list(self.policies),
                "it must include 'braking' (the baseline) and may add "
                f"{', '.join(repr(p) for p in SCRIPTED_POLICIES[1:])}; trained agents are found by themselves",
            )


@dataclass
class NcapConfig(Checked):
    """The Euro NCAP bank (worldmodel/ncap.py): the pedestrian tests and the car-to-car rear tests."""

    # the paper's agents (and braking, the planner) act from this TTC on; before it the car holds its speed
    takeover_ttc_s: float = 1.5
    tests: list[str] = field(default_factory=lambda: ["CPFA-50", "CPNA-25", "CPNA-75", "CPNC-50"])
    speeds_kmh: list[float] = field(default_factory=lambda: [float(v) for v in range(20, 65, 5)])
    # car-to-car: CCRs and CCRm at every car_speed_step_kmh of their speed range and every overlap; CCRb's 4 variants
    car_tests: list[str] = field(default_factory=lambda: ["CCRs", "CCRm", "CCRb"])
    overlaps_pct: list[float] = field(default_factory=lambda: [-75.0, -50.0, 50.0, 75.0, 100.0])
    car_speed_step_kmh: float = 5.0

    def problems(self):
        from envs.ncap import CAR_TESTS, TESTS

        if any(t not in TESTS for t in self.tests):
            yield ConfigValueError("tests", list(self.tests), f"use a list of {', '.join(TESTS)}")
        if any(t not in CAR_TESTS for t in self.car_tests):
            yield ConfigValueError("car_tests", list(self.car_tests), f"use a list of {', '.join(CAR_TESTS)}")
        if not self.tests and not self.car_tests:
            yield ConfigValueError("tests", [], "give at least one pedestrian or car-to-car test")
        if any(not 0 < abs(o) <= 100 for o in self.overlaps_pct) or not self.overlaps_pct:
            yield ConfigValueError("overlaps_pct", list(self.overlaps_pct), "use overlaps in [-100, 0) or (0, 100]")
        if self.car_speed_step_kmh <= 0 or self.car_speed_step_kmh % 5:
            yield ConfigValueError("car_speed_step_kmh", self.car_speed_step_kmh, "use a positive multiple of 5")
        if not self.speeds_kmh or any(not 0 < v <= 150 for v in self.speeds_kmh):
            yield ConfigValueError("speeds_kmh", list(self.speeds_kmh), "use speeds in (0, 150] km/h")
        if not 0.0 < self.takeover_ttc_s <= 4.0:
            yield ConfigValueError(
                "takeover_ttc_s", self.takeover_ttc_s, "it must be in (0, 4] s (the tests start at 4 s)"
            )


PEERS = {
    "chae": "dqn_chae",
    "kim": "ddpg_kim",
    "merola": "ddqn_merola",
}  # peer system -> its agent preset (conf/agent/), on its own family


@dataclass
class ExperimentConfig(Checked):
    """Every stage's config: shared keys, then one section per stage or component."""

    experiment: str = "default"  # names data/${experiment}/ and runs/${experiment}/
    seed: int = 0
    resume: bool = False  # continue from runs/.../last.pt (and finish partial datasets)
    threads: int = 2  # torch intra-op threads
    # load an artifact whose recorded inputs (dataset, VAE, LSTM) differ from the current ones, with a warning
    allow_stale: bool = False
    scale_name: str | None = None  # set by conf/scale/*.yaml
    # the agent presets (conf/agent/<name>.yaml) the pipeline trains, each with the rewards its agent.rewards lists
    # ddpg: the paper's agent (R1 and R2); chooser: the camera agent that beats braking (R2; docs/design.md §5)
    agents: list[str] = field(default_factory=lambda: ["ddpg", "chooser"])
    # training seeds of every preset in agents; empty: seed alone (a seed trained before is kept either way)
    seeds: list[int] = field(default_factory=list)
    # the banks the pipeline's evaluations run on, in order (worldmodel/banks.py): validation for everyday runs;
    # add test only for final numbers, since the ledger records every evaluation on a test bank
    banks: list[str] = field(default_factory=lambda: ["validation"])
    # peer systems the pipeline also trains and evaluates on their own scenario family (pipeline peers=[chae])
    peers: list[str] = field(default_factory=list)
    paths: PathsConfig = field(default_factory=PathsConfig)
    collect: CollectConfig = field(default_factory=CollectConfig)
    demos: DemosConfig = field(default_factory=DemosConfig)
    evaluate: EvaluateConfig = field(default_factory=EvaluateConfig)
    ncap: NcapConfig = field(default_factory=NcapConfig)
    env: EnvConfig = field(default_factory=EnvConfig)
    vae: VAEConfig = field(default_factory=VAEConfig)
    rnn: RNNConfig = field(default_factory=RNNConfig)
    agent: AgentConfig = field(default_factory=AgentConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)

    def problems(self):
        yield from _positive(self, "threads")
        a = self.agent
        for key in ("demo_share", "bc_pretrain_steps", "bc_weight"):
            if getattr(a, key) > 0 and self.demos.episodes < 1:
                yield ConfigValueError(
                    f"agent.{key}", getattr(a, key), "it learns from planner demonstrations: set demos.episodes > 0"
                )
        for name in self.agents:
            if not (CONF_DIR / "agent" / f"{name}.yaml").exists():
                known = sorted(p.stem for p in (CONF_DIR / "agent").glob("*.yaml"))
                yield ConfigValueError("agents", list(self.agents), f"{name!r} is not a preset: use {', '.join(known)}")
        from .banks import BANKS

        if not self.banks or any(b not in BANKS for b in self.banks):
            yield ConfigValueError("banks", list(self.banks), f"give some of {', '.join(BANKS)}")
        unknown = [p for p in self.peers if p not in PEERS]
        if unknown:
            yield ConfigValueError("peers", list(self.peers), f"known peer systems: {', '.join(PEERS)}")
        if a.bc_weight > 0 and a.demo_share == 0:
            yield ConfigValueError(
                "agent.bc_weight", a.bc_weight, "cloning needs demonstrations in the batch: set agent.demo_share > 0"
            )


def register() -> None:
    """Put the schema into Hydra's ConfigStore as ``schema`` (idempotent); ``conf/base.yaml`` starts from it, so
    every group option and override is merged into, and checked against, these dataclasses."""
    ConfigStore.instance().store(name="schema", node=ExperimentConfig)


register()


# ----------------------------------------------------------------------------- validation
def validate(cfg) -> ExperimentConfig:
    """The config as typed dataclasses, after every range check; the first impossible value is a StageError
    naming its key (``agent.tau``, ``evaluate.oracle.replan_every_s``)."""

    for f in fields(ExperimentConfig):
        node = OmegaConf.select(cfg, f.name, throw_on_missing=False)
        if node is None or not OmegaConf.is_config(node) or not is_dataclass(OmegaConf.get_type(node)):
            continue
        try:
            OmegaConf.to_object(node)
        except ConfigValueError as err:
            raise StageError(f"config {f.name}.{err}") from None
    try:
        return OmegaConf.to_object(cfg)
    except ConfigValueError as err:
        raise StageError(f"config {err}") from None


def section(cfg, name: str) -> dict:
    """A config section as a plain dict (resolved), e.g. for recording what an artifact was built with."""
    return OmegaConf.to_container(cfg[name], resolve=True)


# ----------------------------------------------------------------------------- composition and entry points
def compose(stage: str, overrides: list[str] | tuple[str, ...] = ()):
    """Compose the real Hydra config of ``stage`` (for tests and notebooks)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return hydra_compose(config_name=stage, overrides=list(overrides))


def hydra_main(stage: str) -> Callable[[Callable], Callable]:
    """Wrap a stage's ``run(cfg)`` as its command-line entry point.

    ``StageError`` is logged as one readable line and exits with status 2, so a missing input reads as an
    instruction rather than a traceback.
    """
    import hydra

    def decorate(run: Callable):
        if run.__module__ == "__main__" and getattr(sys.modules["__main__"], "__spec__", None) is not None:
            # Under `python -m worldmodel.X` the stage's functions live in __main__, which a launcher's job process
            # (joblib, submitit) cannot import by name, so process pools inside the stage fail to pickle them.
            # Running the copy from the real module keeps every function importable.
            import importlib

            run = getattr(importlib.import_module(sys.modules["__main__"].__spec__.name), run.__name__)

        @hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name=stage)
        def main(cfg):
            return_freed_memory()
            try:
                return run(cfg)
            except StageError as err:
                # through logging, so the job's .log file (and a SLURM job's log) says why it stopped
                logging.getLogger(f"worldmodel.{stage}").error("error: %s", err)
                sys.exit(2)

        return main

    return decorate
