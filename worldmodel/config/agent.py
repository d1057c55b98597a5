"""The agent sections: every learner's keys (DDPG, the chooser, the counterfactual actor, the DQN) and the reward.
Each family's own training keys (``agent.<section>``) are declared by the family (worldmodel/families/<name>/config.py)
and joined from the registry (``family_sections``)."""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from .. import registry
from ..common import Checked, ConfigValueError, worker_count_problems
from ..common import positive_fields as _positive
from ..models.ddpg_config import DDPGSettings, lidar_problems
from ..models.dqn_config import DQNConfig
from .family_sections import with_family_sections

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
    # labelling processes; auto: the cores this process may use. The same labels for any count (tested)
    num_workers: int | str = "auto"
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

    # the labels are equal for any worker count (tested): recorded runs hashed the count they ran with
    RECORDED_WORKERS = 2
    ADDED_OFF = {"label_seed": None, "mask_camera": "wide"}  # each seed its own labels; the world model's camera

    @classmethod
    def as_recorded(cls, values: dict, settings: dict) -> None:
        if values.get("num_workers") is not None:
            values["num_workers"] = cls.RECORDED_WORKERS
        for key in ("min_brake_cost", "static_penalty"):
            if not values.get(key):
                values.pop(key, None)  # off: the chooser as before the option
        super().as_recorded(values, settings)

    def problems(self):
        from envs.chooser import chooser_candidates

        yield from _positive(self, "episodes", "decide_s", "lr", "batch_size", "steps")
        yield from worker_count_problems(self, "num_workers", prefix="chooser.")
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


@dataclass
class CounterfactualConfig(Checked):
    """The counterfactual-cost actor (``agent.learner=counterfactual``; ``envs/counterfactual.py``,
    ``worldmodel/counterfactual.py``): a DDPG actor on [z, zhat, speed] that picks a shift (steer, pedal, duration)
    at each of its decisions, trained against an ensemble critic fitted to the exact costs the simulator gives
    those shifts, on braking's states first and then, round by round, on the actor's own."""

    episodes: int = 1500  # labelled braking episodes (round 0), the last 15 % held out
    dagger_rounds: int = 2  # rounds in which the actor drives and its own states are labelled
    dagger_episodes: int = 500  # labelled actor episodes per round, the last 15 % held out
    # the seed of the labelled scenarios; null: the training seed. Set, the seeds share round 0's labels
    label_seed: int | None = None
    # labelling processes; auto: the cores this process may use. The same labels for any count: each episode draws
    # its scenario and proposals from a seed of its own
    num_workers: int | str = "auto"
    # the labelled scenarios: hazards with this probability, at these speeds and TTCs (the bank's ranges)
    hazard_share: float = 0.85
    speed_range: list[float] = field(default_factory=lambda: [8.0, 30.0])
    ttc_range: list[float] = field(default_factory=lambda: [0.25, 1.5])
    # the actor decides at onset and every interval_s after, decisions times; 0.33 s is 5 frames, within the
    # 0.2-0.4 s in which a second decision still changes where a lane change ends
    decisions: int = 3
    interval_s: float = 0.33
    hold_s: list[float] = field(default_factory=lambda: [0.15, 0.6])  # s: the span of a shift's steering phase
    # what may take over at the next decision in a label (beside the shift running on): braking straight, and
    # shifts at these steers with the chooser's 0.3 s hold, to both sides
    continuation_steers: list[float] = field(default_factory=lambda: [0.3, 1.0])
    continuation_hold_s: float = 0.3
    # shifts labelled per decision state: braking, the actor's choice, local_share of the rest near that choice
    # (Gaussian, local_std in u units) and the others uniform over [-1, 1]^3
    proposals: int = 8
    local_share: float = 0.5
    local_std: float = 0.2
    # the critic: the mean of critic_members MLPs regressing the labelled cost of (state, decision, u)
    critic_members: int = 5
    # what the critic reads: "actor", the actor's own view (the world model's, or the true state with
    # obs=privileged); "privileged", the true state (envs.privileged) whatever the actor reads. The critic only
    # trains the actor and never acts, so it may see what the camera cannot (an asymmetric actor-critic)
    critic_obs: str = "actor"
    critic_hidden: list[int] = field(default_factory=lambda: [256, 256])
    critic_steps: int = 4000  # minibatches per round, refitted from scratch on every label so far
    critic_lr: float = 1.0e-3
    weight_decay: float = 1.0e-4
    batch_size: int = 256
    # the actor: the paper's network (agent.ddpg.actor_hidden), its last layer at zero so that it starts as braking;
    # actor_steps minibatches per round, continuing from the previous round's actor
    actor_steps: int = 2000
    actor_lr: float = 1.0e-3
    # the actor minimises mean + pessimism x spread of the members' predicted costs, plus anchor_weight x
    # (spread / its mean over the minibatch) x |u_steer, u_pedal|^2: where the members disagree it stays near
    # straight-line braking (u = 0), as TD3+BC anchors to its data. 1 and 0.05: of four settings tried on the quick
    # validation banks 4711 and 4712 (these; 2 and 0.2; 0 and 0; 3x the labels), the best pooled share with static
    # collisions at most 2 % (docs/results/phase3/)
    pessimism: float = 1.0
    anchor_weight: float = 0.05
    # policy improvement by search: at every actor minibatch the objective above is also scored at braking and at
    # `search` shifts drawn uniformly over [-1, 1]^3, and the actor regresses (weight search_weight, per unit of
    # squared u distance) towards the cheapest, so that it can leave the basin of the critic it starts in (braking)
    # for a cheaper one that no gradient step reaches. 0 = the gradient alone (DDPG's actor update)
    search: int = 0
    search_weight: float = 1.0
    # the loss weight of heads on the critic's and the actor's first layers that guess the true state
    # (envs.privileged: the hazards, the ego, what blocks each escape path): learning by cheating for perception,
    # as the chooser's head, which took its camera scorer from ~5 % to ~20-30 % of the planner's gain. 0 = no head
    aux_weight: float = 1.0

    ADDED_OFF = {"critic_obs": "actor", "search": 0}

    @classmethod
    def as_recorded(cls, values: dict, settings: dict) -> None:
        if not values.get("search"):
            values.pop("search_weight", None)  # read only by the search
        super().as_recorded(values, settings)

    def problems(self):
        yield from (
            ConfigValueError(f"counterfactual.{e.key}", e.value, e.requirement)
            for e in _positive(
                self,
                "episodes",
                "dagger_episodes",
                "decisions",
                "interval_s",
                "proposals",
                "critic_members",
                "critic_steps",
                "critic_lr",
                "batch_size",
                "actor_steps",
                "actor_lr",
                "continuation_hold_s",
            )
        )
        yield from worker_count_problems(self, "num_workers", prefix="counterfactual.")
        for key in ("hazard_share", "local_share"):
            if not 0.0 <= getattr(self, key) <= 1.0:
                yield ConfigValueError(f"counterfactual.{key}", getattr(self, key), "it must be in [0, 1]")
        for key in ("speed_range", "ttc_range", "hold_s"):
            value = [float(x) for x in getattr(self, key)]
            if len(value) != 2 or not 0 < value[0] <= value[1]:
                yield ConfigValueError(f"counterfactual.{key}", value, "it must be [low, high] with 0 < low <= high")
        if any(not 0.0 < float(s) <= 1.0 for s in self.continuation_steers):
            yield ConfigValueError(
                "counterfactual.continuation_steers", list(self.continuation_steers), "each must lie in (0, 1]"
            )
        for key in (
            "dagger_rounds",
            "local_std",
            "weight_decay",
            "pessimism",
            "anchor_weight",
            "aux_weight",
            "search",
            "search_weight",
        ):
            if not getattr(self, key) >= 0:  # written so that NaN fails too
                yield ConfigValueError(f"counterfactual.{key}", getattr(self, key), "it must be >= 0")
        if self.critic_obs not in ("actor", "privileged"):
            yield ConfigValueError("counterfactual.critic_obs", self.critic_obs, "use actor or privileged")
        if self.proposals < 2:
            yield ConfigValueError("counterfactual.proposals", self.proposals, "it must be >= 2 (braking and one)")
        if not self.critic_hidden or any(int(h) < 1 for h in self.critic_hidden):
            yield ConfigValueError(
                "counterfactual.critic_hidden", list(self.critic_hidden), "use a non-empty list of layer sizes >= 1"
            )

    def label_settings(self, step_s: float) -> dict:
        """What round 0's labels depend on (their store is rebuilt when any of it changes)."""
        return {
            "version": 1,
            "hazard_share": float(self.hazard_share),
            "speed_range": [float(x) for x in self.speed_range],
            "ttc_range": [float(x) for x in self.ttc_range],
            "decisions": int(self.decisions),
            "interval": self.interval(step_s),
            "hold_s": [float(x) for x in self.hold_s],
            "continuations": [vars(m) for m in self.continuations(step_s)],
            "proposals": int(self.proposals),
            "local_share": float(self.local_share),
            "local_std": float(self.local_std),
        }

    def interval(self, step_s: float) -> int:
        """Steps between decisions."""
        return max(1, int(round(float(self.interval_s) / float(step_s))))

    def continuations(self, step_s: float):
        from envs.counterfactual import Shift

        hold = max(1, int(round(float(self.continuation_hold_s) / float(step_s))))
        out = [Shift(0.0, -1.0, 1)]
        for steer in sorted({float(s) for s in self.continuation_steers}):
            out += [Shift(side * steer, -1.0, hold) for side in (1.0, -1.0)]
        return out

    def space(self, step_s: float):
        from envs.counterfactual import ShiftSpace

        return ShiftSpace(tuple(float(x) for x in self.hold_s), float(step_s))


@dataclass
class KimChooserConfig(Checked):
    """The LIDAR chooser on family kim (``agent.learner=kim_chooser``, ``agent=kim_chooser``;
    worldmodel/families/kim/chooser.py): it brakes, and switches once to the manoeuvre whose ``kim_unaware`` cost
    (ISS) an MLP predicts lowest from the LIDAR view. The defaults made the figures of docs/results/kim/."""

    # labelled straight-line braking episodes of the training distribution, the last 15 % held out to choose the
    # epoch; shared by every training seed. 1,500: about a point more than 800 (docs/results/kim/)
    episodes: int = 1500
    # the seed of the labelled scenarios, the same for every training seed: the seeds differ only in the scorer's
    # initialisation and minibatches
    label_seed: int = 0
    decide_s: float = 0.3  # s: the chooser may switch only this early, then it keeps braking
    hidden: int = 256  # units of each of the scorer's two hidden layers
    epochs: int = 60  # passes over the training labels; the epoch kept is the one that avoids most on the held out
    margin: float = 0.0  # ISS (km/h) of predicted saving by which a switch must beat braking

    def problems(self):
        for err in _positive(self, "decide_s", "hidden", "epochs"):
            yield ConfigValueError(f"kim_chooser.{err.key}", err.value, err.requirement)
        if self.episodes < 2:
            yield ConfigValueError("kim_chooser.episodes", self.episodes, "it must be >= 2 (one to fit, one held out)")
        for key in ("label_seed", "margin"):
            if getattr(self, key) < 0:
                yield ConfigValueError(f"kim_chooser.{key}", getattr(self, key), "it must be >= 0")


# what an agent sees: the world model's [z, zhat(, speed)] from the camera, or Chae's privileged 15-value
# pedestrian history (envs/chae.py); a DDPG or chooser agent always sees the world model
# LIDAR scans (Kim), or Merola's last 4 camera frames as frozen VAE means or ResNet-18 features; "privileged": the
# simulator's true state (envs/privileged.py), for the paper's DDPG with the camera taken out of the question
OBSERVATIONS = ("worldmodel", "pedestrian_history", "lidar", "frames_vae", "frames_resnet", "privileged")


@dataclass
class AgentSettings(Checked):
    """Phase 3: the training loop's settings, what the agent sees, and each learner's section (DDPG's
    hyperparameters: ``agent.ddpg``, ``DDPGSettings``, documented there). ``AgentConfig`` below adds each family's
    own section (``agent.<section>``)."""

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
    reward_scale: float = 1.0  # rewards are multiplied by this in the replay (the optimum does not change)
    # the rewards the pipeline trains this preset with (`agents:`); a student that only clones the R2 planner
    # lists r2 alone, since its R1 run would be the same network under another name
    rewards: list[str] = field(default_factory=lambda: ["r1", "r2"])
    # "ddpg" (the paper's learner, agent.ddpg) or "chooser" (agent.chooser: costs of manoeuvres learnt from the
    # simulator's labels; R2 only); "counterfactual", "dqn" and "kim_chooser" below
    learner: str = "ddpg"
    # learner "ddpg": DDPG's (and TD3's) hyperparameters, which Kim et al.'s LIDAR DDPG reads too
    ddpg: DDPGSettings = field(default_factory=DDPGSettings)
    chooser: ChooserConfig = field(default_factory=ChooserConfig)
    # learner "counterfactual": a DDPG actor trained against the simulator's exact costs of its manoeuvres
    counterfactual: CounterfactualConfig = field(default_factory=CounterfactualConfig)
    # learner "kim_chooser" (worldmodel/families/kim/chooser.py): the chooser on family kim, from the LIDAR
    kim_chooser: KimChooserConfig = field(default_factory=KimChooserConfig)
    # learner "dqn" (worldmodel/families/chae/): DQN / Double DQN with a trauma memory over discrete brake levels
    dqn: DQNConfig = field(default_factory=DQNConfig)
    # what the agent sees (OBSERVATIONS; choose with obs=NAME); paper_obs is what its preset's paper gives it: runs
    # with another observation get the suffix -NAME (agent_chae_dqn_chae-worldmodel/seed0)
    obs: str = "worldmodel"
    paper_obs: str = "worldmodel"
    # obs=lidar: the observation holds this many LIDAR scans (oldest first) of lidar_rays rays each, as Kim et al.'s
    # (4 x 36); a DDPG reads them through 1-D convolutions over the angle (models/ddpg_config.py:DDPGConfig), the
    # LIDAR chooser as they are. 0: no LIDAR
    lidar_scans: int = 0
    lidar_rays: int = 36

    ADDED_OFF = {"lidar_scans": 0, "lidar_rays": 36, "obs": "worldmodel", "paper_obs": "worldmodel"}

    @classmethod
    def as_recorded(cls, values: dict, settings: dict) -> None:
        """As ``Checked``'s, and DDPG's keys (``agent.ddpg``) at ``agent.*``, where every recorded run hashed them,
        for every learner."""
        super().as_recorded(values, settings)
        values.update(values.pop("ddpg", None) or {})

    def problems(self):
        from ..action_map import ANCHORS, STEERS

        learners = registry.LEARNERS

        if self.learner not in learners:
            yield ConfigValueError("learner", self.learner, f"it must be one of {', '.join(learners)}")

        yield from lidar_problems(self)
        yield from _positive(self, "checkpoint_every", "reward_scale")
        if self.learner == "ddpg":
            yield from self.total_steps_problems("total_steps", self.total_steps)
        for family in registry.families():  # a family's checks against the agent's other keys
            section = getattr(self, family.section, None) if family.section else None
            if hasattr(section, "agent_problems"):
                yield from section.agent_problems(self)
        if not self.variant.replace("_", "").isalnum() or not self.variant.islower():
            yield ConfigValueError("variant", self.variant, "it must be a lower-case name of letters, digits and _")
        for key in ("obs", "paper_obs"):
            if getattr(self, key) not in OBSERVATIONS:
                yield ConfigValueError(key, getattr(self, key), f"it must be one of {', '.join(OBSERVATIONS)}")
        seen_by = {name: learner.sees for name, learner in learners.items()}
        if self.learner in seen_by and self.obs not in seen_by[self.learner]:
            yield ConfigValueError(
                "obs", self.obs, f"the {self.learner} learner sees one of: {', '.join(seen_by[self.learner])}"
            )
        if self.obs == "privileged":  # the true state alone: it holds the speed, and recorded frames do not hold it
            for key in ("use_speed", "frame_view", "demo_share", "bc_pretrain_steps"):
                if getattr(self, key):
                    yield ConfigValueError(
                        key, getattr(self, key), "obs=privileged reads the true state only: leave it off (0 / false)"
                    )
        for key in ("focus_share", "demo_share"):
            if not 0.0 <= getattr(self, key) <= 1.0:
                yield ConfigValueError(key, getattr(self, key), "it must be in [0, 1]")
        if self.dagger_rounds < 0 or self.dagger_episodes < 1:
            yield ConfigValueError("dagger_rounds", self.dagger_rounds, "rounds must be >= 0, dagger_episodes >= 1")
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

    def total_steps_problems(self, key: str, steps: int):
        """A training length ``steps`` (at config key ``key``) must be > 0, or 0 for an actor cloned and not trained
        further (a ddpg learner with ``bc_pretrain_steps`` > 0)."""
        clones = self.learner == "ddpg" and self.bc_pretrain_steps > 0
        if steps < 0 or (steps == 0 and not clones):
            yield ConfigValueError(key, steps, "it must be > 0 (or 0 with a ddpg learner's bc_pretrain_steps > 0)")


AgentConfig = with_family_sections(AgentSettings, "agent_config", "AgentConfig")

# an override of one of DDPG's keys at agent.* (agent.n_step=3) stops naming its place in agent.ddpg
# (``config.entry.moved_keys``), rather than with Hydra's "not in struct"
MOVED_KEYS = {f"agent.{f.name}": f"agent.ddpg.{f.name}" for f in fields(DDPGSettings)}


@dataclass
class RewardConfig(Checked):
    """R1 = -(n_ped + n_occ) (paper Eq. 7) or R2 = -(sum P_ped + sum P_occ) (Eq. 8); ``envs.rewards``."""

    name: str = "r2"

    def problems(self):
        from envs.rewards import REWARDS

        if self.name not in REWARDS:
            yield ConfigValueError("name", self.name, f"use one of {', '.join('reward=' + r for r in REWARDS)}")
