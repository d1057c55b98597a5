"""Plumbing shared by every stage: clear errors, atomic writes, seeding and building the env.

Paths and loaders live in ``artifacts.py``, config composition in ``config/`` (docs/design.md §2, §9).
"""

from __future__ import annotations

import collections
import contextlib
import functools
import hashlib
import math
import os
import random
import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

CONF_DIR = Path(__file__).resolve().parent.parent / "conf"
PROJECT_ROOT = CONF_DIR.parent


class StageError(RuntimeError):
    """A problem the user can fix (missing input, bad config, corrupt file).

    The message names what is wrong and what to do; stage entry points print it without a traceback.
    """


class NonFiniteLossError(StageError):
    pass


def make_env(cfg, **overrides):
    """The simulator the ``env`` config section describes (``config.EnvConfig``), with the experiment's reward;
    ``overrides`` replace any keyword (``camera=False``, ``horizon_after_ttc_s=None``, ...)."""
    from hydra.utils import instantiate

    return instantiate(cfg.env, **{"reward": cfg.reward.name, **overrides})


def stage_command(stage: str, cfg) -> str:
    """The command a user runs to produce a stage's outputs for this experiment."""
    return f"python -m worldmodel.{stage} experiment={cfg.experiment} scale=<smoke|quick|paper>"


def require(path: Path, what: str, stage: str, cfg) -> Path:
    """Stop at once, naming the missing file and the command that makes it."""
    path = Path(path)
    if not path.exists():
        raise StageError(f"{what} not found at {path}. Run `{stage_command(stage, cfg)}` first.")
    return path


class ConfigValueError(ValueError):
    """An impossible value of one config key (named relative to its section); ``config.validate`` turns it into
    a StageError with the full key."""

    def __init__(self, key: str, value: Any, requirement: str):
        super().__init__(f"{key}={value!r} is impossible: {requirement}")
        self.key, self.value, self.requirement = key, value, requirement


def positive_fields(obj, *keys: str) -> Iterator[ConfigValueError]:
    for key in keys:
        value = getattr(obj, key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
            yield ConfigValueError(key, value, "it must be a positive number")


class Checked:
    """A config dataclass whose ``problems()`` run when it is built (``OmegaConf.to_object`` or directly);
    the first problem is raised.

    A section also says how a run's config hash covers its keys (``as_recorded``, applied by
    worldmodel/config/recorded.py), so that a new option is declared once, where it is defined:

    - ``UNHASHED``: keys that shape no result (a worker count, a permission, a measurement made after training);
    - ``ADDED_OFF``: options added after runs were recorded, each with the value that leaves a run as it was before
      the option; at that value the key stays out of the hash, so recorded runs stay current;
    - ``REMOVED``: keys removed since runs were recorded, with the one value they ever had; put back before hashing.

    (Plain class attributes, not dataclass fields: they are not config keys.)"""

    UNHASHED = ()
    ADDED_OFF = {}
    REMOVED = {}

    def problems(self) -> Iterator[ConfigValueError]:
        return iter(())

    @classmethod
    def as_recorded(cls, values: dict, settings: dict) -> None:
        """``values``, this section as a plain dict, changed in place to how recorded runs hashed it. ``settings``:
        the stage's whole settings, for a rule that depends on another section. A section with a conditional rule
        extends this."""
        for key in cls.UNHASHED:
            values.pop(key, None)
        for key, value in cls.REMOVED.items():
            values.setdefault(key, value)
        for key, off in cls.ADDED_OFF.items():
            if key in values and values[key] == off:
                values.pop(key)

    def __post_init__(self) -> None:
        for problem in self.problems():
            raise problem


# ----------------------------------------------------------------------------- files
TEMPORARY = ".{name}.tmp-{pid}"  # the one temporary-file scheme: hidden, next to its target, named by writer


@contextlib.contextmanager
def atomic_output(path: Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; when the block succeeds it is fsynced and renamed onto ``path``.

    Readers therefore see the old file or the whole new one, never a part. A failed block removes the
    temporary file; a killed process leaves it behind for ``clean_temporaries``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(TEMPORARY.format(name=path.name, pid=os.getpid()))
    try:
        yield tmp
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def _alive(pid: int) -> bool:
    """Whether a process ``pid`` runs on this machine (signal 0 checks without signalling)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # it exists, under another user
        return True
    return True


class LockHeldError(StageError):
    """Another process holds the writer lock of the folder a stage would write."""


_HELD_LOCKS: dict[Path, tuple[Any, int]] = {}  # lock file -> (its open handle, how many holders in this process)


@contextlib.contextmanager
def writer_lock(directory: Path, what: str):
    """Hold the one-writer lock of ``directory`` (an output a stage writes) while the block runs.

    An exclusive advisory lock (``flock``) on ``.<name>.lock`` beside the directory, so that retiring the directory
    leaves it in place. A second process that asks for it is refused at once with a StageError naming the holder.
    The kernel drops the lock when its process ends, however it ends, so a killed run leaves nothing to clear. In
    one process the lock is re-entrant (the pipeline holds it around a stage that takes it again)."""
    import fcntl
    import sys

    directory = Path(directory).absolute()
    path = directory.parent / f".{directory.name}.lock"
    if path in _HELD_LOCKS:
        handle, count = _HELD_LOCKS[path]
        _HELD_LOCKS[path] = (handle, count + 1)
    else:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle = open(path, "a+")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip() or "a process that has not said which"
            handle.close()
            raise LockHeldError(
                f"{directory} is being written by another process ({holder}). Wait for it to end, or stop it: two "
                f"writers of {what} would mix their files."
            ) from None
        handle.seek(0)
        handle.truncate()
        handle.write(f"pid {os.getpid()}: {' '.join(sys.argv) or 'python'}, since {time.strftime('%H:%M:%S')}")
        handle.flush()
        _HELD_LOCKS[path] = (handle, 1)
    try:
        yield
    finally:
        handle, count = _HELD_LOCKS[path]
        if count > 1:
            _HELD_LOCKS[path] = (handle, count - 1)
        else:
            del _HELD_LOCKS[path]
            handle.close()  # closing the file releases the lock


def lock_holder(directory: Path) -> str | None:
    """Who holds ``directory``'s writer lock (``writer_lock``): the holder's own line, or None when it is free."""
    import fcntl

    directory = Path(directory).absolute()
    path = directory.parent / f".{directory.name}.lock"
    if path in _HELD_LOCKS or not path.exists():
        return None
    with open(path, "a+") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            return handle.read().strip() or "another process"
        fcntl.flock(handle, fcntl.LOCK_UN)
    return None


def clean_temporaries(directory: Path, name: str = "*") -> int:
    """Remove what writers killed inside ``atomic_output`` left in ``directory`` (for target files ``name``).

    A temporary file is named by its writer's pid: one whose writer still runs on this machine (another stage or
    pipeline writing the same folder, or this process) is in use and is left alone."""
    removed = 0
    for tmp in Path(directory).glob(TEMPORARY.format(name=name, pid="*")):
        pid = tmp.name.rsplit(".tmp-", 1)[-1]
        if pid.isdigit() and (int(pid) == os.getpid() or _alive(int(pid))):
            continue
        tmp.unlink(missing_ok=True)
        removed += 1
    return removed


def atomic_write_bytes(path: Path, data: bytes) -> None:
    with atomic_output(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def atomic_torch_save(obj: Any, path: Path) -> None:
    """``torch.save`` to ``path`` atomically, every tensor on the CPU, so that a checkpoint loads on any device."""
    import io

    import torch

    buf = io.BytesIO()
    torch.save(interned(to_cpu(obj)), buf)
    atomic_write_bytes(path, buf.getvalue())


def interned(obj: Any) -> Any:
    """``obj`` with every string in its dicts, lists and tuples interned and every array's dtype numpy's own instance
    (the containers rebuilt, their attributes kept). Pickle writes an object it has seen once and refers back to it
    after, so a state holding equal strings (or dtypes) as one object or as copies saves to different bytes: a config
    unpickled in a job process holds copies where the pipeline's own holds one, and an array loaded from a checkpoint
    has a dtype of its own where a new one shares numpy's. Interned, the same content saves to the same bytes, and
    so has the same digest, however it was built (a run resumed, or one that ran straight through)."""
    import sys

    import numpy as np

    if type(obj) is str:
        return sys.intern(obj)
    if type(obj) is np.ndarray and obj.dtype.fields is None:
        canonical = np.dtype(obj.dtype.str)
        return obj if canonical is obj.dtype or canonical != obj.dtype else obj.view(canonical)
    if type(obj) in (dict, collections.OrderedDict):
        out = type(obj)((interned(k), interned(v)) for k, v in obj.items())
        for name, value in getattr(obj, "__dict__", {}).items():  # a state_dict's _metadata
            setattr(out, name, interned(value))
        return out
    if type(obj) is list:
        return [interned(v) for v in obj]
    if type(obj) is tuple:
        return tuple(interned(v) for v in obj)
    return obj


def _off_cpu(obj: Any) -> bool:
    import torch

    if isinstance(obj, torch.Tensor):
        return obj.device.type != "cpu"
    if isinstance(obj, dict):
        return any(_off_cpu(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return any(_off_cpu(v) for v in obj)
    return False


def to_cpu(obj: Any) -> Any:
    """``obj`` with every tensor in its dicts, lists and tuples moved to the CPU; ``obj`` itself when all are
    there already, so a CPU run saves exactly what it did before devices existed."""
    import torch

    if not _off_cpu(obj):
        return obj
    if isinstance(obj, torch.Tensor):
        return obj.cpu()
    if isinstance(obj, dict):
        out = {k: to_cpu(v) for k, v in obj.items()}
        return type(obj)(out) if type(obj) is not dict else out
    if isinstance(obj, (list, tuple)):
        moved = [to_cpu(v) for v in obj]
        return type(obj)(moved) if not hasattr(obj, "_fields") else type(obj)(*moved)
    return obj


# auto | cpu | cuda | cuda:N (the ``device`` setting)
DEVICE_SETTING = re.compile(r"auto|cpu|cuda(:\d+)?")


def resolve_device(setting: str, key: str = "device"):
    """The torch device of the ``device`` setting (or of ``key``, another setting of its form): ``auto`` is CUDA
    when torch sees it and the CPU otherwise. A CUDA device this machine lacks stops the stage before any work (a
    StageError, exit status 2), naming the setting."""
    import torch

    setting = str(setting)
    if not DEVICE_SETTING.fullmatch(setting):
        raise StageError(f"{key}={setting}: use auto, cpu, cuda or cuda:N")
    if setting == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if setting.startswith("cuda"):
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        index = int(setting.partition(":")[2] or 0)
        if index >= count:
            raise StageError(
                f"{key}={setting}: torch sees {count or 'no'} CUDA device{'s' if count != 1 else ''} on this machine "
                f"(torch {torch.__version__}); use {key}=cpu (or {key}=auto, which picks CUDA only where it exists)"
            )
    return torch.device(setting)


def decision_device(cfg):
    """Where evaluation's single decisions run: the ``decision_device`` setting (the CPU where a config lacks it)."""
    return resolve_device(getattr(cfg, "decision_device", "cpu"), "decision_device")


AMP_SETTINGS = ("off", "bf16")  # the ``amp`` setting


def check_amp(amp: str, device) -> None:
    """Refuse ``amp=bf16`` off CUDA: on the CPU it would silently train another model more slowly, not faster."""
    if amp == "bf16" and device.type != "cuda":
        raise StageError(
            f"amp=bf16 runs on a CUDA device only, and this run's device is {device}: use amp=off (or device=cuda "
            "on a machine with a GPU)"
        )


def autocast(device, amp: str):
    """The context that runs a forward pass and its loss in ``amp``'s precision: bf16 autocast on CUDA, else
    nothing at all, so a run without it computes exactly what it did before the setting."""
    import torch

    if amp == "bf16" and device.type == "cuda":
        return torch.autocast(device_type="cuda", dtype=torch.bfloat16)
    return contextlib.nullcontext()


def module_device(module):
    """The device a module's parameters live on."""
    return next(module.parameters()).device


# ----------------------------------------------------------------------------- worker counts
def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS tells it, as under taskset or a SLURM
    allocation), else the machine's count."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # macOS, Windows
        return max(1, os.cpu_count() or 1)


def worker_count_problems(obj, *keys: str, prefix: str = "") -> Iterator[ConfigValueError]:
    """A worker count is a positive integer or ``auto``; ``prefix`` names a subsection (``chooser.``)."""
    for key in keys:
        value = getattr(obj, key)
        if value == "auto":
            continue
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            yield ConfigValueError(prefix + key, value, "it must be a positive integer or auto (the usable cores)")


def resolve_workers(value: int | str) -> int:
    """A worker-count setting as a number: ``auto`` is the usable cores (``usable_cores``)."""
    return usable_cores() if value == "auto" else int(value)


@contextlib.contextmanager
def worker_pool(workers: int):
    """A ``multiprocessing`` pool of ``workers`` spawned processes. When the block ends normally the pool is closed
    and joined: every worker exits on its own and runs its exit handlers, which unlink and unregister the named
    semaphores it created (tqdm's lock, made by any tqdm, even a disabled one). ``Pool``'s own context manager
    terminates its workers instead, and the resource tracker then reports those semaphores as leaked when the run
    ends. An exception in the block still terminates the workers at once."""
    import multiprocessing as mp

    with mp.get_context("spawn").Pool(workers) as pool:
        yield pool
        pool.close()
        pool.join()


def resolve_loader_workers(value: int | str, device) -> int:
    """The ``loader_workers`` setting as a number for ``device``: ``auto`` reads in the training process on the CPU
    (0: its cores are busy training), and ahead of a CUDA device in the usable cores less the training one, at
    most 4."""
    if value != "auto":
        return int(value)
    return 0 if device.type != "cuda" else max(0, min(4, usable_cores() - 1))


@functools.lru_cache(maxsize=256)
def _sha256(path: str, size: int, mtime_ns: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's bytes (cached per path, size and modification time: checkpoints are hashed often)."""
    st = os.stat(path)
    return _sha256(str(Path(path).resolve()), st.st_size, st.st_mtime_ns)


def load_checkpoint(path: Path, what: str, stage: str, cfg) -> dict:
    """Load a checkpoint written by ``atomic_torch_save``, building nothing but tensors, plain data and numpy arrays
    (``checkpoints.read_checkpoint``); a missing, unreadable or unsafe one is a StageError."""
    from .checkpoints import read_checkpoint

    require(path, what, stage, cfg)
    try:
        return read_checkpoint(path)
    except StageError:
        raise
    except Exception as err:  # truncated or not a torch file
        raise StageError(
            f"{what} at {path} cannot be read ({type(err).__name__}: {err}). Delete {Path(path).parent} (the "
            f"run that wrote it) and rerun `{stage_command(stage, cfg)}`, or run the pipeline, which rebuilds it."
        ) from err


# ----------------------------------------------------------------------------- seeding
def seed_everything(seed: int) -> None:
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def rng_state() -> dict:
    import torch

    return {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}


def set_rng_state(state: dict) -> None:
    import torch

    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])


def return_freed_memory(threshold: int = 1 << 20) -> bool:
    """Serve allocations above ``threshold`` bytes with their own mmap, returned to the OS when freed.

    glibc raises this threshold each time a large block is freed, after which torch's tens-of-MB temporaries
    (a one-hot batch is 54 MB) come from the heap and fragment it: encoding the paper-scale dataset grew the
    process by ~1 MB per episode (278 MB over 300 episodes, 20 MB with this). No-op off glibc."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        M_MMAP_THRESHOLD = -3
        return bool(libc.mallopt(M_MMAP_THRESHOLD, int(threshold)))
    except (OSError, AttributeError):
        return False


def percent(share: float | None) -> str:
    """A share in [0, 1] as a log line's percentage; "n/a" without one (no episode to count)."""
    return "n/a" if share is None else f"{100 * share:.0f} %"


def set_threads(n: int) -> None:
    import torch

    torch.set_num_threads(max(1, int(n)))


REUSED_BLOCK_BYTES = 1 << 28  # blocks up to this size are reused from the heap instead of mapped afresh


def reuse_freed_memory() -> bool:
    """Have glibc keep freed blocks of up to ``REUSED_BLOCK_BYTES`` for reuse instead of unmapping them. By default a
    block over 32 MB is mapped when allocated and unmapped when freed, so a training step that allocates the same
    large activations every minibatch (the chooser's frame-band convolutions: 42 MB each) faults their pages in
    again each time: a third of the chooser's fit went to the kernel (benchmarks/RESULTS.md). Where the arithmetic
    happens is unchanged, so are the results. Returns whether it applied (glibc only; elsewhere nothing changes)."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3
    return bool(mallopt(m_mmap_threshold, REUSED_BLOCK_BYTES)) and bool(mallopt(m_trim_threshold, REUSED_BLOCK_BYTES))


def check_finite(value: float, what: str, step: int, last_good: Path | None) -> None:
    """Stop on a NaN/inf loss; the last good checkpoint on disk is left untouched, and named only if there is one."""
    if not math.isfinite(value):
        if last_good is not None and Path(last_good).exists():
            where = f"the last good checkpoint is {last_good}. Lower the learning rate or check the data, then resume "
            where += "with resume=true."
        else:
            where = "no checkpoint was saved before it. Lower the learning rate or check the data, then run again."
        raise NonFiniteLossError(f"{what} became {value} at step {step}. Training stopped; {where}")


def cached(fn):
    return functools.lru_cache(maxsize=None)(fn)


def read_shards(paths, keys) -> dict:
    """The datasets ``keys`` of the HDF5 shards ``paths``, each concatenated over the shards in order; an unreadable
    shard stops with its name and the way out (delete it, and the stage labels it again)."""
    import h5py

    data: dict[str, list] = {k: [] for k in keys}
    for p in paths:
        try:
            with h5py.File(p, "r") as f:
                for k in data:
                    data[k].append(f[k][...])
        except (OSError, KeyError) as err:
            raise StageError(f"{p} is not a readable label shard ({err}); delete it and rerun to relabel it") from None
    return {k: np.concatenate(v) for k, v in data.items()}
