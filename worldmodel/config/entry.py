"""The ways in: validation of a composed config, agent presets as ``train_agent`` composes them, the planner's
settings, ``compose`` for tests and notebooks and ``hydra_main`` for the stage commands."""

from __future__ import annotations

import copy
import errno
import functools
import json
import logging
import math
import os
import sys
from collections import OrderedDict
from collections.abc import Callable, Iterator
from dataclasses import fields, is_dataclass
from pathlib import Path

from hydra.experimental.callback import Callback
from omegaconf import OmegaConf

from .. import registry
from ..common import CONF_DIR, ConfigValueError, StageError, check_amp, resolve_device, return_freed_memory
from .experiment import ExperimentConfig, agent_presets


def agent_preset(cfg, name: str):
    """The ``agent`` section as ``train_agent scale=<cfg's scale> agent=<name>`` composes it (Hydra's own defaults
    lists: the schema, the scale, then the preset and the presets it builds on). The preset the config was composed
    with keeps its command-line overrides."""
    if cfg.agent.variant == name:
        return cfg.agent
    return _composed_preset(name, cfg.get("scale_name")).agent


def preset_globals(name: str) -> dict:
    """What an agent preset sets outside ``agent`` (a peer's preset, ``# @package _global_``, also picks its
    scenario family, step and reward: conf/agent/dqn_chae.yaml): every value composing it changes there."""
    base = OmegaConf.to_container(_composed_preset(None, None), resolve=False)
    preset = OmegaConf.to_container(_composed_preset(name, None), resolve=False)
    return _changed({k: v for k, v in base.items() if k != "agent"}, {k: v for k, v in preset.items() if k != "agent"})


def _changed(before: dict, after: dict) -> dict:
    """The keys of ``after`` whose values differ from ``before``'s, nested sections compared key by key."""
    out = {}
    for key, value in after.items():
        if isinstance(value, dict) and isinstance(before.get(key), dict):
            inner = _changed(before[key], value)
            if inner:
                out[key] = inner
        elif before.get(key, _changed) != value:
            out[key] = value
    return out


@functools.cache
def _composed_preset(name: str | None, scale: str | None):
    """``train_agent``'s config composed with ``agent=<name>`` (the default preset when None) at ``scale`` (none
    when None); cached, since the pipeline asks for each preset many times."""
    if name is not None and name not in agent_presets():
        raise StageError(
            f"agent variant {name!r} has no preset {CONF_DIR / 'agent' / name}.yaml: restore it, or move its runs aside"
        )
    overrides = [f"agent={name}"] if name else []
    overrides.append(f"scale={scale}" if scale else "~scale")
    return compose("train_agent", overrides)


def peer_preset(name: str) -> str | None:
    """The agent preset a ``peers`` entry names: a peer family's paper preset (``kim`` -> ddpg_kim), or any preset
    of a peer family by its own name (``ddpg_kim_fd``); None when it is neither."""
    known = registry.peers()
    if name in known:
        return known[name]
    if name not in agent_presets():
        return None
    return name if preset_globals(name).get("env", {}).get("family") in known else None


def oracle_settings(cfg) -> dict:
    """``evaluate.oracle`` as plain keyword arguments of ``PrivilegedPlanner.from_settings``."""
    o = cfg.evaluate.oracle
    settings = {
        "replan_every_s": o.replan_every_s,
        "brake_first": o.brake_first,
        "pedals": list(o.pedals),
        "steers": list(o.steers),
        "delays_s": list(o.delays_s),
        "lane_change_s": list(o.lane_change_s),
    }
    sides = list(o.sides)
    if sides != [1.0, -1.0]:  # absent = both sides, so records made before the option still match
        settings["sides"] = sides
    step_s = cfg.env.step_s
    if step_s != 1.0 / 15.0:  # absent = the default step, for the same reason
        settings["step_s"] = step_s
    return settings


def teacher_settings(cfg) -> dict:
    """The planner that records demonstrations and labels DAgger states: ``evaluate.oracle`` planning from the first
    frame, steering to ``demos.teacher_sides`` after ``demos.teacher_delays_s`` (``PrivilegedPlanner.from_settings``
    keyword arguments)."""
    settings = {k: v for k, v in oracle_settings(cfg).items() if k not in ("brake_first", "sides")}
    sides = list(cfg.demos.teacher_sides)
    if sides != [1.0, -1.0]:  # absent = both sides, so records made before the option still match
        settings["sides"] = sides
    delays = cfg.demos.get("teacher_delays_s")
    if delays is not None:
        settings["delays_s"] = list(delays)
    return settings


# ----------------------------------------------------------------------------- validation
def non_finite_settings(node, prefix: str = "") -> Iterator[tuple[str, float]]:
    """Every float setting under ``node`` (a resolved container) that is NaN or infinite, by its full key. No setting
    means either, and NaN would pass every range check (each comparison with it is false)."""
    if isinstance(node, dict):
        for key, value in node.items():
            yield from non_finite_settings(value, f"{prefix}{key}.")
    elif isinstance(node, list):
        for k, value in enumerate(node):
            yield from non_finite_settings(value, f"{prefix[:-1]}[{k}].")
    elif isinstance(node, float) and not math.isfinite(node):
        yield prefix[:-1], node


VALIDATED_KEPT = 32  # configs whose typed form validate keeps: a pipeline's stages, an evaluation's policies
_validated: OrderedDict[str, ExperimentConfig] = OrderedDict()


def validate(cfg) -> ExperimentConfig:
    """The config as typed dataclasses, after every range check; the first impossible value is a StageError
    naming its key (``agent.ddpg.tau``, ``evaluate.oracle.replan_every_s``).

    A config validated before (the same values, schema and registered families and learners) is not checked again:
    a copy of its typed form comes back, about ten times faster, so that code far from a stage's entry may ask for
    the typed config instead of being handed it."""
    resolved = OmegaConf.to_container(cfg, resolve=True)
    resolved.pop("hydra", None)
    schema = [OmegaConf.get_type(cfg, f.name).__name__ if f.name in cfg else None for f in fields(ExperimentConfig)]
    known = [registry.names(), list(registry.LEARNERS)]
    key = json.dumps([resolved, schema, OmegaConf.get_type(cfg).__name__, known], sort_keys=True, default=str)
    if key in _validated:
        _validated.move_to_end(key)
        return copy.deepcopy(_validated[key])
    typed = _checked(cfg, resolved)
    _validated[key] = copy.deepcopy(typed)
    while len(_validated) > VALIDATED_KEPT:
        _validated.popitem(last=False)
    return typed


def _checked(cfg, resolved: dict) -> ExperimentConfig:
    for key, value in non_finite_settings(resolved):
        raise StageError(f"config {key}={value!r} is impossible: it must be a finite number")
    for f in fields(ExperimentConfig):
        _check_section(OmegaConf.select(cfg, f.name, throw_on_missing=False), f.name)
    try:
        typed = OmegaConf.to_object(cfg)
    except ConfigValueError as err:
        raise StageError(f"config {err}") from None
    if isinstance(typed, ExperimentConfig):
        if any(peer_preset(p) is None for p in typed.peers):
            known = ", ".join(registry.peers())
            requirement = f"name a peer system ({known}) or an agent preset of one (e.g. ddpg_kim_fd)"
            raise StageError(f"config {ConfigValueError('peers', list(typed.peers), requirement)}")
        # a CUDA device this machine lacks, or bf16 off CUDA, stops here, before any work
        check_amp(typed.amp, resolve_device(typed.device))
        resolve_device(typed.decision_device, "decision_device")
    return typed


def _check_section(node, path: str) -> None:
    """Build the section ``node`` at ``path`` (``agent``) and the sections inside it, innermost first, so that an
    impossible value is named by its full key (``agent.ddpg.tau``, not ``agent.tau``)."""
    if node is None or not OmegaConf.is_config(node) or not is_dataclass(OmegaConf.get_type(node)):
        return
    for key in node:
        _check_section(OmegaConf.select(node, str(key), throw_on_missing=False), f"{path}.{key}")
    try:
        OmegaConf.to_object(node)
    except ConfigValueError as err:
        raise StageError(f"config {_full_key(path, err.key)}={err.value!r} is impossible: {err.requirement}") from None


def _full_key(path: str, key: str) -> str:
    """A section's key under its path: ``agent.ddpg`` + ``tau``; a section that names its keys from its own name on
    (``chooser.margin`` under ``agent.chooser``) is not named twice."""
    outer, inner = path.split("."), key.split(".")
    overlap = max((n for n in range(1, min(len(outer), len(inner)) + 1) if outer[-n:] == inner[:n]), default=0)
    return ".".join(outer + inner[overlap:])


def section(cfg, name: str) -> dict:
    """A config section as a plain dict (resolved), e.g. for recording what an artifact was built with."""
    return OmegaConf.to_container(cfg[name], resolve=True)


# ----------------------------------------------------------------------------- composition and entry points
def moved_keys(overrides) -> None:
    """A StageError naming the new key of the first override (``agent.n_step=3``, ``+agent.n_step=3``,
    ``~agent.n_step``) that names a key since moved (``agent.MOVED_KEYS``)."""
    from .agent import MOVED_KEYS

    for override in overrides:
        key = str(override).lstrip("+~").split("=", 1)[0]
        if key in MOVED_KEYS:
            raise StageError(f"{key} is now {MOVED_KEYS[key]}: write {str(override).replace(key, MOVED_KEYS[key], 1)}")


COMPOSED_KEPT = 256  # composed configs that compose keeps, one per stage and choice of config groups
_composed: OrderedDict[str, object] = OrderedDict()


def compose(stage: str, overrides: list[str] | tuple[str, ...] = ()):
    """Compose the real Hydra config of ``stage`` (for tests and notebooks).

    Each call returns a config of its own. Hydra composes once per stage and choice of config groups (``scale=``,
    ``agent=``, ...), per state of the files in ``conf/`` and per the names in Hydra's ConfigStore; a later call
    copies that config and applies its other overrides (``seed=1``, ``agent.total_steps=300``) with Hydra's own
    code, as Hydra applies them after composing, about six times faster. An edit to ``conf/`` composes afresh."""
    moved_keys(overrides)
    state, groups = _conf_state()
    chosen, values = _split_overrides([str(o) for o in overrides], groups)
    key = json.dumps([stage, chosen, state])
    if key not in _composed:
        _composed[key] = _hydra_compose(stage, chosen)
        while len(_composed) > COMPOSED_KEPT:
            _composed.popitem(last=False)
    _composed.move_to_end(key)
    cfg = copy.deepcopy(_composed[key])
    if values:
        from hydra._internal.config_loader_impl import ConfigLoaderImpl

        ConfigLoaderImpl._apply_overrides_to_config(values, cfg)  # Hydra's last step of a composition, as it is
    return cfg


def _split_overrides(overrides: list[str], groups: set[str]) -> tuple[list[str], list]:
    """``overrides`` as (what Hydra composes with: choices of config ``groups`` and anything unusual, the parsed
    value changes applied after). Only a plain change of a value outside ``hydra.`` is applied after; a sweep, an
    addition, a deletion, a package or text Hydra's parser refuses stays with the composition, which says what it
    means."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import OverrideType

    try:
        parsed = OverridesParser.create().parse_overrides(overrides=overrides)
    except Exception:  # noqa: BLE001 - Hydra's composition raises its own error for it
        return overrides, []
    chosen, values = [], []
    for text, override in zip(overrides, parsed):
        key = override.key_or_group
        plain = override.type == OverrideType.CHANGE and override.package is None and not override.is_sweep_override()
        if plain and key not in groups and key.split(".")[0] != "hydra":
            values.append(override)
        else:
            chosen.append(text)
    return chosen, values


def _conf_state() -> tuple[list, set[str]]:
    """What a composition reads besides its arguments, and the config groups it has: every file under ``conf/``
    (name, size, modification time) and every name in Hydra's ConfigStore; the folders under ``conf/``
    (``hydra/launcher`` for a nested one) and the ConfigStore's groups."""
    from hydra.core.config_store import ConfigStore

    files, groups = [], set()
    for folder, _, names in os.walk(CONF_DIR):
        relative = os.path.relpath(folder, CONF_DIR)
        if relative != ".":
            groups.add(relative)
        for name in sorted(names):
            stat = os.stat(os.path.join(folder, name))
            files.append((os.path.normpath(os.path.join(relative, name)), stat.st_size, stat.st_mtime_ns))

    def names(node: dict, prefix: str) -> list:
        out = []
        for name, child in sorted(node.items()):
            if isinstance(child, dict):
                groups.add(prefix + name)
                out.append([name, names(child, prefix + name + "/")])
            else:
                out.append([name, []])
        return out

    return [sorted(files), names(ConfigStore.instance().repo, "")], groups


def _hydra_compose(stage: str, overrides: list[str]):
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():  # inside a stage's hydra.main: its search path is CONF_DIR already
        return hydra_compose(config_name=stage, overrides=overrides)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return hydra_compose(config_name=stage, overrides=overrides)


ROOT_KEYS = ("paths.runs_root", "paths.data_root")  # every stage writes under these two folders
DISK_ERRORS = {errno.ENOSPC: "the disk is full", errno.EDQUOT: "the disk quota is used up"}
UNWRITABLE_ERRORS = {errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOTDIR}


def unwritable(path: Path) -> str | None:
    """Why nothing can be written under ``path`` (a folder that may not exist yet), or None: its nearest existing
    ancestor must be a folder this process may write into."""
    existing = Path(path).absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return f"{existing} is a file, not a folder"
    if not os.access(existing, os.W_OK):
        return f"{existing} is read-only here"
    return None


def disk_error_sentence(err: OSError, stage: str) -> str | None:
    """One sentence for a stage stopped by the disk (full, read-only, not writable), or None for other errors."""
    where = err.filename or "its output"
    if err.errno in DISK_ERRORS:
        return (
            f"{stage} stopped writing {where}: {DISK_ERRORS[err.errno]}. What was finished before is kept; free "
            "space, then rerun the same command with resume=true."
        )
    if err.errno in UNWRITABLE_ERRORS:
        return (
            f"{stage} cannot write {where} ({err.strerror}): make that folder writable, or point paths.runs_root / "
            "paths.data_root at one that is."
        )
    return None


class WritableRoots(Callback):
    """A Hydra callback (``conf/base.yaml``: ``hydra.callbacks``): before Hydra makes its run folder under
    ``paths.runs_root``, both roots must be writable; otherwise one sentence names the root and the fix, and the
    command exits 2 with nothing written (Hydra itself would stop with a chained traceback)."""

    def _check(self, config) -> None:
        for key in ROOT_KEYS:
            root = OmegaConf.select(config, key)
            why = None if root is None else unwritable(Path(root))
            if why:
                sentence = f"error: {key}={root} cannot be written: {why}. Point {key} at a writable folder."
                print(sentence, file=sys.stderr)
                sys.exit(2)

    def on_run_start(self, config, **kwargs) -> None:
        self._check(config)

    def on_multirun_start(self, config, **kwargs) -> None:
        self._check(config)


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
            from ..banks import commit

            commit()  # the ledger names the code checked out now, when the run starts
            try:
                return run(cfg)
            except StageError as err:
                # through logging, so the job's .log file (and a SLURM job's log) says why it stopped
                logging.getLogger(f"worldmodel.{stage}").error("error: %s", err)
                sys.exit(2)
            except OSError as err:
                sentence = disk_error_sentence(err, stage)
                if sentence is None:
                    raise
                logging.getLogger(f"worldmodel.{stage}").error("error: %s", sentence)
                sys.exit(2)

        @functools.wraps(main)
        def entry():
            try:  # before Hydra reads the command line, whose error would not name the key's new place
                moved_keys(sys.argv[1:])
            except StageError as err:
                print(f"error: {err}", file=sys.stderr)
                sys.exit(2)
            return main()

        return entry

    return decorate
