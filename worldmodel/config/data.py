"""The data sections: where runs live, the collecting autopilot and its branches, the planner's demonstrations
and the scene (env)."""

from __future__ import annotations

from dataclasses import dataclass, field

from .. import registry
from ..common import Checked, ConfigValueError, worker_count_problems
from ..common import positive_fields as _positive


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
    # simulator processes; auto: the cores this process may use. The shards are the same for any count (tested)
    num_workers: int | str = "auto"
    episodes_per_shard: int = 16
    max_episode_s: float = 15.0  # the paper's 15 s sequences at 15 FPS
    validation_fraction: float = 0.1  # share of episodes held out, stored in split.json
    autopilot: AutopilotConfig = field(default_factory=AutopilotConfig)
    branch: BranchConfig = field(default_factory=BranchConfig)

    def problems(self):
        yield from _positive(self, "episodes", "episodes_per_shard", "max_episode_s")
        yield from worker_count_problems(self, "num_workers")
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
    # simulator processes; auto: the cores this process may use. The same demonstrations for any count (tested)
    num_workers: int | str = "auto"
    episodes_per_shard: int = 25
    focus: FocusConfig = field(default_factory=FocusConfig)
    # the sides evaluate.oracle's planner may steer to (1 right, -1 left); one side removes the ambiguity that a
    # least-squares student averages into braking straight. Stored apart: data/NAME/demos_right/ for [1.0]
    teacher_sides: list[float] = field(default_factory=lambda: [1.0, -1.0])
    # s, the teacher's steering delays in place of evaluate.oracle.delays_s (null: those); [0.0] makes every DAgger
    # label say what to do now. Stored apart (data/NAME/demos_delays0/); no effect on family kim (docs/results/kim/)
    teacher_delays_s: list[float] | None = None

    def problems(self):
        yield from _positive(self, "episodes_per_shard")
        yield from worker_count_problems(self, "num_workers")
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
    # How the camera draws road users narrower than a pixel (the views of conf/view/; docs/design.md §3). false: one
    # sample per pixel, as TinyRenderer draws (the paper's frame, where a pedestrian 30 m ahead is ~0.6 px wide and
    # missing from half the frames); true: every pixel a road user's box covers in part shows it (~0.2 ms a frame)
    road_user_cover: bool = False
    # render at this many times the size and pool each block, a road user in any sub-pixel winning (the cover's
    # reference: 1 = off; 4 costs ~10x the step time, so no view uses it for training)
    supersample: int = 1
    horizon_after_ttc_s: float | None = 3.0  # agent episodes: truncated this long after the sampled TTC
    mu: float = 1.0  # tyre-road friction coefficient (friction circle radius mu*g)
    occupants_per_car: int = 1
    step_s: float = 1.0 / 15.0  # seconds per step: the paper's 15 FPS (Chae, Kim and Merola step 0.1 s)
    # the scenarios reset() samples: the paper's family (the registry's default), or another of envs/families.py
    family: str = registry.default().name
    # metres from the street's centre line (|y|) beyond which an episode ends as left_scene, at no further cost.
    # 25 m lies past every static body of the street (buildings reach 20.5 m), so only an ego that already got
    # through (the side street's opening, a gap between buildings) leaves; a huge value lets such episodes go on
    lateral_exit_m: float = 25.0

    ADDED_OFF = {
        "step_s": 1.0 / 15.0,
        "tele_fov_deg": None,
        "lateral_exit_m": 25.0,
        "road_user_cover": False,
        "supersample": 1,
    }

    @classmethod
    def as_recorded(cls, values: dict, settings: dict) -> None:
        from ..registry import default

        if values.get("family") == default().name:
            values.pop("family")  # the paper's scenes, as before the families existed
        super().as_recorded(values, settings)

    def problems(self):
        if self.image_size != 64:
            yield ConfigValueError("image_size", self.image_size, "the VAE's encoder takes 64x64 frames")
        yield from _positive(self, "mu", "occupants_per_car", "lateral_exit_m")
        if not 1 <= self.supersample <= 8:
            yield ConfigValueError("supersample", self.supersample, "use 1 (off) to 8 sub-pixels a side")
        if not 10.0 <= self.fov_deg <= 170.0:
            yield ConfigValueError("fov_deg", self.fov_deg, "the camera's field of view must be in [10, 170] degrees")
        if self.tele_fov_deg is not None and not 10.0 <= self.tele_fov_deg <= 170.0:
            yield ConfigValueError("tele_fov_deg", self.tele_fov_deg, "it must be in [10, 170] degrees, or null")
        if not 0.0 < self.step_s <= 0.5:
            yield ConfigValueError("step_s", self.step_s, "it must be in (0, 0.5] seconds")
        from envs.families import names

        known = names()
        if self.family not in known:
            yield ConfigValueError("family", self.family, f"it must be one of {', '.join(known)}")
        if self.horizon_after_ttc_s is not None and self.horizon_after_ttc_s <= 0:
            yield ConfigValueError("horizon_after_ttc_s", self.horizon_after_ttc_s, "it must be > 0 (or null)")
