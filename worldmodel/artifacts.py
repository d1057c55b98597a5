"""The experiment's artifacts: where each one lives, how it is loaded, what it was built from, and when it is done.

Stages are peers: each reads its inputs and writes its outputs through this module and never imports another
stage (``tests/test_layout.py``). The layout of ``experiment=NAME`` (docs/design.md §9)::

    data/NAME/rollouts/          collect      (complete when manifest.json exists)
    data/NAME/latents.h5         train_rnn    (the dataset encoded by one VAE checkpoint; rebuilt when it changes)
    runs/NAME/vae/               train_vae    best.pt, last.pt, metrics.json (complete), provenance.json
    runs/NAME/rnn/               train_rnn    same files
    runs/NAME/agent_r1/seed0/    train_agent  same files (last.pt is the actor that is evaluated)
    runs/NAME/eval/              evaluate     results.csv, tables.md, heatmaps.png, summary.json (complete)
    runs/NAME/stale/             outputs the pipeline set aside because their inputs changed

**Provenance.** A model's identity is the SHA-256 of its defining file (``best.pt``, an agent's ``last.pt``); a
dataset's is the SHA-256 of its manifest's content without the collection's timings (``dataset_sha256``). Each
training stage records the identities of its inputs and a hash of the config keys that shape it, in
``provenance.json`` (written when the run starts) and in every checkpoint; when it finishes it adds the digests of
its checkpoints (``outputs``). Loading a model compares the recorded inputs with the current ones, and the file
with the digest its run recorded: a mismatch stops with a ``StageError`` naming the files and the command that
rebuilds the stale one, unless ``allow_stale=true`` (then a warning). The pipeline compares the same records to
decide which stages to rerun. Records made before a dataset was its content, or before outputs were recorded, are
read as written (``legacy_identities``; no digest, no comparison).

**One writer.** A stage holds its output directory's lock while it writes, and the pipeline its experiment's
(``common.writer_lock``): a second writer is refused at once, naming the first.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from envs import rewards

from . import registry
from .common import StageError, atomic_write_text, file_sha256
from .config.recorded import as_recorded, inputs_as_recorded

log = logging.getLogger(__name__)

PROVENANCE = "provenance.json"


# ----------------------------------------------------------------------------- paths
def data_dir(cfg) -> Path:
    return Path(cfg.paths.data)


def runs_root(cfg) -> Path:
    return Path(cfg.paths.runs)


def rollouts_dir(cfg) -> Path:
    return data_dir(cfg) / "rollouts"


def manifest_path(cfg) -> Path:
    return rollouts_dir(cfg) / "manifest.json"


def demos_dir(cfg) -> Path:
    """``data/NAME/demos/``, or ``demos_<teacher>/`` for a teacher other than evaluate.oracle's planner steering
    both ways (``demos.teacher_sides``, ``demos.teacher_delays_s``; e.g. ``demos_right/``)."""
    from .config import validate

    teacher = validate(cfg).demos.teacher_name()
    return data_dir(cfg) / ("demos_" + teacher if teacher else "demos")


def uses_demos(agent) -> bool:
    """Whether an agent with the config section ``agent`` learns from the planner's demonstrations (or its DAgger
    labels)."""
    return agent.demo_share > 0 or agent.bc_pretrain_steps > 0


def latents_path(cfg) -> Path:
    return data_dir(cfg) / "latents.h5"


def vae_dir(cfg) -> Path:
    return runs_root(cfg) / "vae"


def rnn_dir(cfg) -> Path:
    return runs_root(cfg) / "rnn"


def eval_dir(cfg) -> Path:
    """Where an evaluation writes: ``runs/NAME/eval`` for the paper's family and ``runs/NAME/eval_<family>`` for
    another, on the family's default validation draw; ``_test`` added for the sealed test bank and ``_seed<N>`` for
    another validation draw (worldmodel/banks.py)."""
    from .banks import dir_suffix

    family = registry.family(cfg.evaluate.get("family") or registry.default().name)
    seed = family.validation_seed(cfg)
    return runs_root(cfg) / (family.folder + dir_suffix(cfg.evaluate.bank, family.name, seed))


def stale_dir(cfg) -> Path:
    return runs_root(cfg) / "stale"


# ----------------------------------------------------------------------------- agent naming
PAPER_VARIANT = "ddpg"  # conf/agent/ddpg.yaml, the paper's agent: its runs keep the plain name agent_r1


@dataclass(frozen=True, order=True)
class AgentId:
    """One trained agent: its reward, training seed, variant (the ``conf/agent/<variant>.yaml`` preset it was
    trained with) and observation. ``key`` (``agent_r1/seed0``, ``agent_r2_fd/seed1``,
    ``agent_chae_dqn_chae-worldmodel/seed0``) names it in evaluation rows, on disk under ``runs/NAME/`` and in the
    pipeline; ``policy`` (``agent_r1``, ``agent_r2_fd``) pools its seeds in the reports. The paper's variant has no
    suffix, and ``obs`` is empty (no suffix) when the agent sees what its preset's paper gives it."""

    reward: str
    seed: int
    variant: str = PAPER_VARIANT
    obs: str = ""

    @property
    def policy(self) -> str:
        suffix = "" if self.variant == PAPER_VARIANT else f"_{self.variant}"
        return f"agent_{self.reward}{suffix}" + (f"-{self.obs}" if self.obs else "")

    @property
    def key(self) -> str:
        return f"{self.policy}/seed{self.seed}"

    @property
    def family(self) -> str:
        """The scenario family the agent was trained and is evaluated on (its reward's)."""
        return registry.of_reward(self.reward).name

    def dir(self, cfg) -> Path:
        return runs_root(cfg) / self.key

    @classmethod
    def parse(cls, key: str) -> AgentId:
        policy, _, seed = key.partition("/seed")
        policy, _, obs = policy.partition("-")
        name = policy.removeprefix("agent_")
        # run names are agent_<reward>...: any registered reward (envs/rewards.py); reward names may hold
        # underscores: the longest registered one that the name starts with
        known = [r for r in rewards.REWARDS if name == r or name.startswith(f"{r}_")]
        if not policy.startswith("agent_") or not known or not seed.isdigit():
            raise ValueError(f"{key!r} does not name an agent (expected e.g. 'agent_r1/seed0' or 'agent_r2_fd/seed0')")
        reward = max(known, key=len)
        return cls(reward, int(seed), name[len(reward) + 1 :] or PAPER_VARIANT, obs)

    @classmethod
    def of(cls, cfg) -> AgentId:
        """The agent that ``train_agent`` with this config trains."""
        a = cfg.agent
        obs = a.get("obs", "worldmodel")
        return cls(cfg.reward.name, cfg.seed, a.variant, "" if obs == a.get("paper_obs", obs) else obs)


def agent_dir(cfg) -> Path:
    return AgentId.of(cfg).dir(cfg)


def trained_agents(cfg, family: str | None = None) -> list[AgentId]:
    """Every agent of the experiment with a checkpoint that belongs to scenario ``family`` (the default family when
    None), sorted (reward, then seed)."""
    family = family or registry.default().name
    found = []
    for path in runs_root(cfg).glob("agent_*/seed*/last.pt"):
        try:
            agent = AgentId.parse(f"{path.parent.parent.name}/{path.parent.name}")
        except ValueError:
            continue
        if agent.family == family:
            found.append(agent)
    return sorted(found)


# ----------------------------------------------------------------------------- identity
def short(sha: str | None) -> str:
    return (sha or "")[:12]


def config_sha256(settings: Any) -> str:
    return hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode()).hexdigest()


def file_identity(path: Path) -> str | None:
    return file_sha256(path) if path.exists() else None


# A dataset manifest's fields that say how the collection went on this machine, not what it holds: they are left
# out of the dataset's identity, so that the same data recorded twice has one identity.
MANIFEST_TIMING = ("wall_s", "frames_per_s_this_run")


@functools.lru_cache(maxsize=16)
def _dataset_sha256(path: str, size: int, mtime_ns: int) -> str:
    manifest = json.loads(Path(path).read_text())
    manifest.pop("digests", None)  # the shards' bytes are checked against these; their content is already here
    manifest["summary"] = {k: v for k, v in manifest.get("summary", {}).items() if k not in MANIFEST_TIMING}
    return config_sha256(manifest)


def dataset_sha256(manifest: Path) -> str | None:
    """A dataset's identity: SHA-256 of its manifest's content (episodes, lengths, outcomes) without the timing
    fields and shard digests; None when the manifest is absent."""
    if not manifest.exists():
        return None
    st = os.stat(manifest)
    return _dataset_sha256(str(Path(manifest).resolve()), st.st_size, st.st_mtime_ns)


DATASETS = ("rollouts", "demos")  # provenance inputs that are datasets, identified by ``dataset_sha256``


def dataset_manifests(cfg) -> dict[str, Path]:
    return {"rollouts": manifest_path(cfg), "demos": demos_dir(cfg) / "manifest.json"}


def legacy_identities(files: dict[str, Path]) -> dict[str, str]:
    """The identity of each dataset among ``files`` (input name -> manifest) in records made when a dataset's
    identity was its manifest file's bytes: a record holding one still names the dataset as it is, read so."""
    return {name: file_sha256(path) for name, path in files.items() if name in DATASETS and Path(path).exists()}


def rollouts_id(cfg) -> str | None:
    return dataset_sha256(manifest_path(cfg))


def vae_id(cfg) -> str | None:
    return file_identity(vae_dir(cfg) / "best.pt")


def rnn_id(cfg) -> str | None:
    return file_identity(rnn_dir(cfg) / "best.pt")


def actor_id(cfg, agent: AgentId) -> str | None:
    return file_identity(agent.dir(cfg) / "last.pt")


# ----------------------------------------------------------------------------- what each stage is built from
def _section(cfg, key: str):
    from omegaconf import OmegaConf

    value = OmegaConf.select(cfg, key)
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


def _config(cfg, *keys: str) -> dict:
    return {key: _section(cfg, key) for key in keys}


def provenance(cfg, stage: str, agent: AgentId | None = None) -> dict:
    """The current inputs of ``stage`` (``vae``, ``rnn``, ``agent``, ``eval``) and the hash of its config keys
    (which keys count, and how: each section declares it, worldmodel/config/recorded.py)."""
    if stage == "vae":
        inputs, settings = {"rollouts": rollouts_id(cfg)}, _config(cfg, "seed", "vae")
    elif stage == "rnn":
        inputs, settings = {"rollouts": rollouts_id(cfg), "vae": vae_id(cfg)}, _config(cfg, "seed", "rnn")
    elif stage == "agent":
        agent = agent or AgentId.of(cfg)
        uses_world_model = cfg.agent.get("obs", "worldmodel") == "worldmodel"
        inputs = {name: identity(cfg) for name, identity in world_model_inputs(cfg.agent.get("obs", "worldmodel"))}
        settings = {**_config(cfg, "agent", "env"), "reward": agent.reward, "seed": agent.seed}
        if uses_demos(cfg.agent) and not uses_world_model:
            # a LIDAR agent's demonstrations are made in-process by the planner (worldmodel/families/kim/): what
            # makes them is part of its settings, not an input on disk
            from .config import teacher_settings

            demos = _config(cfg, "demos")["demos"]
            settings["demos"] = {k: demos[k] for k in ("episodes", "teacher_sides")}
            if demos.get("teacher_delays_s") is not None:  # absent = evaluate.oracle's, as before the option
                settings["demos"]["teacher_delays_s"] = demos["teacher_delays_s"]
            settings["teacher"] = teacher_settings(cfg)
        elif uses_demos(cfg.agent):
            inputs["demos"] = dataset_sha256(demos_dir(cfg) / "manifest.json")
        street = uses_world_model or cfg.agent.get("obs") == "privileged"  # train_agent's own loop
        if street and (uses_demos(cfg.agent) or cfg.agent.focus_share > 0):
            settings["focus"] = _config(cfg, "demos")["demos"]["focus"]  # the focus mix's ranges shape the training
    elif stage == "eval":
        family = registry.family(cfg.evaluate.get("family") or registry.default().name)
        inputs = {a.key: actor_id(cfg, a) for a in trained_agents(cfg, family.name)}
        settings = _config(cfg, "evaluate", "env")
    else:
        raise ValueError(f"no provenance for stage {stage!r}")
    return {"inputs": inputs, "config": config_sha256(as_recorded(settings))}


def read_provenance(directory: Path) -> dict | None:
    path = Path(directory) / PROVENANCE
    try:
        return json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def write_provenance(directory: Path, record: dict) -> None:
    atomic_write_text(Path(directory) / PROVENANCE, json.dumps(record, indent=2, sort_keys=True))


def differences(recorded: dict | None, current: dict, legacy: dict[str, str] | None = None) -> list[str]:
    """Human-readable reasons why ``recorded`` no longer matches ``current`` (empty: up to date). ``legacy``: the
    datasets' identities as older records wrote them (``legacy_identities``), taken as the current ones."""
    if recorded is None:
        return ["no record of its inputs"]
    out = []
    inputs = inputs_as_recorded(recorded.get("inputs", {}), current["inputs"])
    for name, now in current["inputs"].items():
        then = inputs.get(name)
        if then != now and not (then is not None and then == (legacy or {}).get(name)):
            out.append(f"{name} {short(then) or 'absent'} -> {short(now) or 'absent'}")
    for name in set(inputs) - set(current["inputs"]):
        out.append(f"{name} {short(inputs[name])} -> absent")
    if recorded.get("config") != current["config"]:
        out.append("its config changed")
    return out


def retire(cfg, directory: Path) -> Path | None:
    """Move a stale stage directory under ``runs/NAME/stale/`` (nothing is deleted); returns where it went."""
    directory = Path(directory)
    if not directory.exists():
        return None
    rel = directory.relative_to(runs_root(cfg))
    target = stale_dir(cfg) / f"{str(rel).replace('/', '-')}-{time.strftime('%Y%m%d-%H%M%S')}"
    n = 1
    while target.exists():
        target = target.with_name(f"{target.name}.{n}")
        n += 1
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.move(str(directory), str(target))
    return target


def refuse_unless_allowed_stale(cfg, message: str) -> None:
    """A StageError with ``message``, or under ``allow_stale=true`` a warning and on."""
    if cfg.get("allow_stale", False):
        log.warning("allow_stale=true: %s", message)
        return
    raise StageError(message)


# ----------------------------------------------------------------------------- outputs
CHECKPOINTS = ("best.pt", "last.pt")  # a training run's files whose digests its record keeps once it finished


def output_digests(directory: Path) -> dict[str, str]:
    """SHA-256 of each checkpoint a training run left in ``directory``: recorded when it finishes."""
    return {name: file_sha256(Path(directory) / name) for name in CHECKPOINTS if (Path(directory) / name).exists()}


def changed_outputs(directory: Path) -> list[str]:
    """How a finished run's checkpoints differ from the files it wrote (empty: unchanged, or a run finished before
    its outputs were recorded, which is read as written)."""
    recorded = (read_provenance(directory) or {}).get("outputs") or {}
    out = []
    for name, then in sorted(recorded.items()):
        now = file_identity(Path(directory) / name)
        if now != then:
            out.append(f"{name} {short(then)} -> {short(now) or 'absent'} after its run finished")
    return out


def check_output(cfg, path: Path, what: str, rebuild: str) -> None:
    """Refuse a checkpoint that is not the file its finished run wrote (changed by hand, by a disk or by another
    process): its metrics and everything built on it describe another model. ``allow_stale=true``: a warning."""
    recorded = ((read_provenance(Path(path).parent) or {}).get("outputs") or {}).get(Path(path).name)
    if recorded is None or not Path(path).exists() or file_sha256(path) == recorded:
        return
    message = (
        f"{what} {path} is not the file its run wrote (SHA-256 {short(recorded)} when the run finished, now "
        f"{short(file_sha256(path))}), so its metrics describe another model. Restore the file, or delete "
        f"{Path(path).parent} and rerun `{rebuild}` (the pipeline sets such a run aside and rebuilds it and what "
        "was built on it); allow_stale=true loads it anyway."
    )
    refuse_unless_allowed_stale(cfg, message)


def world_model_inputs(obs: str) -> list[tuple[str, Any]]:
    """(name, identity function) of the world-model parts an agent's observation ``obs`` reads: the VAE and the LSTM
    for the world model's view, the VAE alone for the frozen VAE's means of the frames (``frames_vae``), none for a
    privileged or LIDAR view or ResNet features."""
    if obs == "worldmodel":
        return [("vae", vae_id), ("rnn", rnn_id)]
    return [("vae", vae_id)] if obs == "frames_vae" else []


# ----------------------------------------------------------------------------- completion
def output_dir(cfg, stage: str, agent: AgentId | None = None) -> Path:
    """Where ``stage`` (``collect``, ``vae``, ``rnn``, ``agent``, ``eval``) writes."""
    if stage == "agent":
        return (agent or AgentId.of(cfg)).dir(cfg)
    return {"collect": rollouts_dir, "demos": demos_dir, "vae": vae_dir, "rnn": rnn_dir, "eval": eval_dir}[stage](cfg)


def marker(cfg, stage: str, agent: AgentId | None = None) -> Path:
    """The file whose existence means ``stage`` finished."""
    done = {"collect": "manifest.json", "demos": "manifest.json", "eval": "summary.json"}.get(stage, "metrics.json")
    return output_dir(cfg, stage, agent) / done
