"""The whole schema: every section under one ``ExperimentConfig``, registered in Hydra's ConfigStore."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from hydra.core.config_store import ConfigStore

from ..common import CONF_DIR, Checked, ConfigValueError
from ..common import positive_fields as _positive
from .agent import AgentConfig, RewardConfig
from .data import CollectConfig, DemosConfig, EnvConfig, PathsConfig
from .evaluation import EvaluateConfig, NcapConfig
from .world_model import RNNConfig, VAEConfig

# an experiment names folders under data/ and runs/: one plain folder name, so that it never writes into runs/ itself
# or outside it
EXPERIMENT_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]*")
LAUNCHERS = ("inline", "local", "slurm")  # how the pipeline runs its steps (worldmodel/launcher.py)


def agent_presets() -> list[str]:
    """Every name ``agent=<name>`` takes: a file ``conf/agent/<name>.yaml``, or a preset a plugin put into Hydra's
    ConfigStore (group ``agent``, package ``_global_``: docs/design.md §11)."""
    stored = ConfigStore.instance().repo.get("agent", {})
    return sorted({p.stem for p in (CONF_DIR / "agent").glob("*.yaml")} | {n.removesuffix(".yaml") for n in stored})


@dataclass
class ExperimentConfig(Checked):
    """Every stage's config: shared keys, then one section per stage or component."""

    experiment: str = "default"  # names data/${experiment}/ and runs/${experiment}/
    seed: int = 0
    resume: bool = False  # continue from runs/.../last.pt (and finish partial datasets)
    threads: int = 2  # torch intra-op threads
    # where torch trains and decides: auto (CUDA when torch sees it, else the CPU), cpu, cuda or cuda:N. Never part of
    # a provenance hash: checkpoints hold CPU tensors, so a model trained on one device loads on any other
    device: str = "auto"
    # where evaluation's batch-1 decisions run (the same values as device): cpu keeps the fast decision path of
    # worldmodel/models/fast_decision.py, which a GPU has to beat per decision, not per batch; benchmarks/gpu_check.py
    # measures 1,000 decisions on each. Never part of a provenance hash: the decisions are the same numbers
    decision_device: str = "cpu"
    # mixed precision of the VAE's and the LSTM's training: off (float32) or bf16 (bfloat16 autocast, CUDA only;
    # refused elsewhere). Off by default: bf16 trains a slightly different model, and nothing has measured how much.
    # Never part of a provenance hash, like device
    amp: str = "off"
    # processes that read and decompress the VAE's HDF5 frames ahead of a CUDA device, into pinned memory; the data
    # and their order are the same for any count. auto: none on the CPU (the training process reads them, as its
    # cores are busy training), and the usable cores less one, at most 4, on CUDA
    loader_workers: int | str = "auto"
    # load an artifact whose recorded inputs (dataset, VAE, LSTM) differ from the current ones, with a warning
    allow_stale: bool = False
    scale_name: str | None = None  # set by conf/scale/*.yaml
    # the agent presets (conf/agent/<name>.yaml) the pipeline trains, each with the rewards its agent.rewards lists
    # ddpg: the paper's agent (R1 and R2); chooser: the camera agent that beats braking (R2); counterfactual: the
    # DDPG actor trained against the simulator's exact costs of its manoeuvres (R2; docs/design.md §5).
    # Empty: the paper's family is left out, neither trained nor evaluated (a run of peers alone)
    agents: list[str] = field(default_factory=lambda: ["ddpg", "chooser", "counterfactual"])
    # training seeds of every preset in agents; empty: seed alone (a seed trained before is kept either way)
    seeds: list[int] = field(default_factory=list)
    # the banks the pipeline's evaluations run on, in order (worldmodel/banks.py): validation for everyday runs;
    # add test only for final numbers, since the ledger records every evaluation on a test bank
    banks: list[str] = field(default_factory=lambda: ["validation"])
    # peer systems the pipeline also trains, at every seed of seeds, and evaluates on their own scenario family, per
    # bank of banks: a family (chae: its paper's preset) or another preset of one (ddpg_kim_fd); empty: none
    peers: list[str] = field(default_factory=list)
    # the pipeline only: list each step's state (complete, resume, fresh, stale and why, or after a step that runs
    # first) and the recorded wall time of the finished ones, and run nothing; for a long run, where it stands
    plan: bool = False
    # the pipeline only: how its steps run. inline: one after another in this process. local: as processes on
    # this machine, up to launcher_jobs at once, each on its own share of the cores (worker counts left at auto
    # follow it). slurm: each step a SLURM job with conf/hydra/launcher/slurm.yaml's resources, up to launcher_jobs
    # at once. Steps run together only when none reads another's output (worldmodel/launcher.py)
    launcher: str = "inline"
    # steps at once under launcher=local or slurm; 2 on 2 cores gives each step one
    launcher_jobs: int = 2
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
        if not EXPERIMENT_NAME.fullmatch(str(self.experiment)):
            yield ConfigValueError(
                "experiment", self.experiment, "name it with letters, digits, '.', '_' or '-', not starting with '.'"
            )
        for key, values in (("seed", [self.seed]), ("seeds", list(self.seeds))):
            if any(isinstance(v, bool) or not isinstance(v, int) or v < 0 for v in values):
                value = self.seed if key == "seed" else values
                yield ConfigValueError(key, value, "seeds are whole numbers >= 0 (numpy's generators take no other)")
        yield from _positive(self, "threads")
        yield from _positive(self, "launcher_jobs")
        if self.launcher not in LAUNCHERS:
            yield ConfigValueError("launcher", self.launcher, f"use {', '.join(LAUNCHERS)}")
        from ..common import AMP_SETTINGS, DEVICE_SETTING

        for key in ("device", "decision_device"):
            if not DEVICE_SETTING.fullmatch(str(getattr(self, key))):
                yield ConfigValueError(key, getattr(self, key), "use auto, cpu, cuda or cuda:N")
        if self.amp not in AMP_SETTINGS:
            yield ConfigValueError("amp", self.amp, f"use {' or '.join(AMP_SETTINGS)} (bf16: CUDA only)")
        if self.loader_workers != "auto" and (
            isinstance(self.loader_workers, bool) or not isinstance(self.loader_workers, int) or self.loader_workers < 0
        ):
            yield ConfigValueError(
                "loader_workers", self.loader_workers, "use auto or a number >= 0 (0: read in the training process)"
            )
        a = self.agent
        for key, value in (
            ("demo_share", a.demo_share),
            ("bc_pretrain_steps", a.bc_pretrain_steps),
            ("ddpg.bc_weight", a.ddpg.bc_weight),
        ):
            if value > 0 and self.demos.episodes < 1:
                yield ConfigValueError(
                    f"agent.{key}", value, "it learns from planner demonstrations: set demos.episodes > 0"
                )
        for name in self.agents:
            if name not in agent_presets():
                known = ", ".join(agent_presets())
                yield ConfigValueError("agents", list(self.agents), f"{name!r} is not a preset: use {known}")
        from ..banks import BANKS

        if not self.banks or any(b not in BANKS for b in self.banks):
            yield ConfigValueError("banks", list(self.banks), f"give some of {', '.join(BANKS)}")
        # whether each `peers` entry names a peer's preset needs the presets composed: config.validate checks it
        if a.ddpg.bc_weight > 0 and a.demo_share == 0:
            yield ConfigValueError(
                "agent.ddpg.bc_weight",
                a.ddpg.bc_weight,
                "cloning needs demonstrations in the batch: set agent.demo_share > 0",
            )


def register() -> None:
    """Put the schema into Hydra's ConfigStore as ``schema`` (idempotent); ``conf/base.yaml`` starts from it, so
    every group option and override is merged into, and checked against, these dataclasses."""
    ConfigStore.instance().store(name="schema", node=ExperimentConfig)


register()
