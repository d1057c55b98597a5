"""The HDF5 rollout store: schema, atomic shard writing, validation and streaming readers.

Layout of ``data/NAME/rollouts/`` (schema version 2; documented in ``data/README.md``)::

    collect_config.json     what produced the shards (checked on resume)
    split.json              {"train": [episode ids], "validation": [episode ids]}, a seeded draw
    shard_00000.h5 ...      episodes [k * per_shard, (k + 1) * per_shard), visible only once complete
    manifest.json           written last: the collection is complete

Each shard holds one group per episode, ``episode_000123``, with

* ``seg (T, 64, 64) uint8``  class ids 0..12 (see ``envs.CLASS_NAMES``); T observations including the first
  and the last,
* ``speed (T,) float32``     ego speed (m/s) at each observation,
* ``action (T, 2) float32``  ``action[t]`` is the action taken after seeing ``seg[t]``; the last row has no
  action and is zero (``attrs["n_steps"] == T - 1`` actions are real),
* ``reward_r1``, ``reward_r2`` ``(T,) float32``: reward received for ``action[t]`` (last row 0),
* ``done (T,) uint8``          1 where the episode ended after ``action[t]`` (row T-2), and on the padding row,

and attributes ``index``, ``seed``, ``scenario`` (JSON of ``envs.ScenarioSpec``), ``outcome`` (JSON), ``n_steps``,
``terminated``, ``branch_of`` and ``branch_step``. File attributes: ``schema_version``, ``episodes`` (ids),
``class_names``, ``dt``.

**Branched episodes** (schema 2, ``collect.branch``): a counterfactual continuation of episode ``p`` from its step
``t0``, recorded by restoring the simulator's snapshot and holding one action. It is an episode of its own, id
``episodes + p * branch.actions + j``, with ``branch_of = p`` and ``branch_step = t0`` (-1 for the recorded
episodes); its first ``context + 1`` frames and ``context`` actions are copied from ``p`` so that the LSTM has a
warm-up. It belongs to its parent's split. ``manifest.json`` maps each branch id to its parent. Schema 1 stores
(before branches) are still read; they hold no branches.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np

from .common import atomic_output

SCHEMA_VERSION = 2
READABLE_VERSIONS = (1, 2)  # 1: before branched episodes (no branch attributes); read as a store without branches
EPISODE_KEYS = ("seg", "speed", "action", "reward_r1", "reward_r2", "done")
SHARD_GLOB = "shard_*.h5"


class CorruptDataError(RuntimeError):
    """A shard is unreadable or does not follow the schema. The message names the file."""


def shard_name(k: int) -> str:
    return f"shard_{k:05d}.h5"


def episode_key(i: int) -> str:
    return f"episode_{i:06d}"


# ----------------------------------------------------------------------------- writing
def write_shard(path: Path, episodes: list[dict], meta: dict) -> None:
    """Write a whole shard under a temporary name, then rename: readers never see a partial file."""
    with atomic_output(path) as tmp, h5py.File(tmp, "w", track_order=True) as f:
        f.attrs["schema_version"] = SCHEMA_VERSION
        f.attrs["episodes"] = np.array([e["index"] for e in episodes], dtype=np.int64)
        for key, value in meta.items():
            f.attrs[key] = value
        for ep in episodes:
            g = f.create_group(episode_key(ep["index"]))
            n = len(ep["seg"])
            g.create_dataset(
                "seg",
                data=ep["seg"],
                chunks=(min(n, 32), *ep["seg"].shape[1:]),
                compression="gzip",
                compression_opts=4,
                shuffle=True,
                track_times=False,
            )
            for key in EPISODE_KEYS[1:]:
                g.create_dataset(key, data=ep[key], track_times=False)
            for key in ("index", "seed", "n_steps", "terminated"):
                g.attrs[key] = ep[key]
            g.attrs["branch_of"] = int(ep.get("branch_of", -1))
            g.attrs["branch_step"] = int(ep.get("branch_step", -1))
            g.attrs["scenario"] = ep["scenario"]
            g.attrs["outcome"] = ep["outcome"]


# ----------------------------------------------------------------------------- reading / validation
def _open(path: Path) -> h5py.File:
    try:
        return h5py.File(path, "r")
    except Exception as err:
        raise CorruptDataError(
            f"{path} is not a readable HDF5 shard ({err}). It is corrupt or truncated: rerun the "
            "collection with resume=true, which sets it aside and records it again."
        ) from err


def check_shard(path: Path, full: bool = True) -> list[int]:
    """Check one shard against the schema; with ``full`` read every frame. Returns its episode ids."""
    f = _open(path)
    try:
        with f:
            version = f.attrs.get("schema_version")
            version = int(version) if version is not None else None
            if version not in READABLE_VERSIONS:
                raise CorruptDataError(
                    f"{path} has schema_version {version!r}; this code reads versions "
                    f"{', '.join(map(str, READABLE_VERSIONS))} (data/README.md). Recollect it with this version: "
                    "delete the rollouts folder and run `python -m worldmodel.collect experiment=NAME`."
                )
            ids = [int(i) for i in f.attrs["episodes"]]
            for i in ids:
                g = f.get(episode_key(i))
                if g is None:
                    raise CorruptDataError(f"{path}: episode {i} is listed but missing")
                missing = [k for k in EPISODE_KEYS if k not in g]
                if missing:
                    raise CorruptDataError(f"{path}: episode {i} lacks {missing}")
                n = g["seg"].shape[0]
                if any(g[k].shape[0] != n for k in EPISODE_KEYS) or int(g.attrs["n_steps"]) != n - 1:
                    raise CorruptDataError(f"{path}: episode {i} has inconsistent lengths")
                if full:
                    for k in EPISODE_KEYS:
                        g[k][...]
            return ids
    except CorruptDataError:
        raise
    except Exception as err:
        raise CorruptDataError(
            f"{path} is corrupt or truncated ({type(err).__name__}: {err}). Rerun the collection with "
            "resume=true, which sets it aside and records it again."
        ) from err


class RolloutStore:
    """Read access to a complete rollout directory. Opens shards lazily, one handle per process."""

    def __init__(self, root: Path, check: bool = True):
        self.root = Path(root)
        manifest = self.root / "manifest.json"
        if not manifest.exists():
            raise FileNotFoundError(f"{manifest} is missing: the collection in {self.root} is not complete")
        self.manifest = json.loads(manifest.read_text())
        self.split = json.loads((self.root / "split.json").read_text())
        self.shards = sorted(self.root.glob(SHARD_GLOB))
        # branched episode id -> the recorded episode it continues (none in a schema-1 store)
        self.branch_of = {int(k): int(v) for k, v in self.manifest.get("branches", {}).items()}
        expected = set(range(self.manifest["episodes"])) | set(self.branch_of)
        self.location: dict[int, Path] = {}
        for path in self.shards:
            ids = check_shard(path, full=False) if check else [int(i) for i in _open(path).attrs["episodes"]]
            for i in ids:
                self.location[i] = path
        if set(self.location) != expected:
            lost = sorted(expected - set(self.location))[:10]
            raise CorruptDataError(
                f"{self.root}: episodes {lost} are missing from the shards; rerun the collection with resume=true"
            )
        self._handles: dict[Path, h5py.File] = {}
        self._pid = os.getpid()
        self.lengths = {i: self.manifest["lengths"][str(i)] for i in expected}

    def _file(self, path: Path) -> h5py.File:
        if os.getpid() != self._pid:  # a forked worker must not share HDF5 handles
            self._handles, self._pid = {}, os.getpid()
        if path not in self._handles:
            self._handles[path] = _open(path)
        return self._handles[path]

    def read(self, i: int, key: str, sl=slice(None)) -> np.ndarray:
        path = self.location[i]
        try:
            return self._file(path)[episode_key(i)][key][sl]
        except CorruptDataError:
            raise
        except Exception as err:
            raise CorruptDataError(
                f"{path}: reading episode {i}/{key} failed ({err}); the file is corrupt. "
                "Rerun the collection with resume=true, which sets it aside and records it again."
            ) from err

    def attrs(self, i: int) -> dict:
        g = self._file(self.location[i])[episode_key(i)]
        return {k: g.attrs[k] for k in g.attrs}

    def episodes(self, split: str, branches: bool = True) -> list[int]:
        """The split's recorded episodes and, with ``branches``, the branched continuations of them."""
        main = list(self.split[split])
        if not branches or not self.branch_of:
            return main
        members = set(main)
        return main + sorted(i for i, p in self.branch_of.items() if p in members)

    def frames(self, split: str) -> int:
        return sum(self.lengths[i] for i in self.episodes(split))

    def close(self) -> None:
        for f in self._handles.values():
            f.close()
        self._handles = {}


def frame_pools(
    store: RolloutStore, episodes: list[int], rng: np.random.Generator, block: int = 32, buffer_blocks: int = 16
) -> list[tuple[list[tuple[int, int]], np.ndarray]]:
    """The shuffle of one pass over ``episodes``, drawn from ``rng`` before any frame is read: random contiguous
    blocks of ``block`` frames, ``buffer_blocks`` at a time in a pool, each pool with the permutation of its
    frames. Every reader of the pass (this process or loader workers) reads the same pools in the same order."""
    units = [(i, s) for i in episodes for s in range(0, store.lengths[i], block)]
    order = rng.permutation(len(units))
    pools = []
    for first in range(0, len(order), buffer_blocks):
        blocks = [units[u] for u in order[first : first + buffer_blocks]]
        frames = sum(min(block, store.lengths[i] - s) for i, s in blocks)
        pools.append((blocks, rng.permutation(frames)))
    return pools


def read_pool(store: RolloutStore, pool: tuple[list[tuple[int, int]], np.ndarray], block: int = 32) -> np.ndarray:
    """A pool's frames, read and shuffled."""
    blocks, permutation = pool
    return np.concatenate([store.read(i, "seg", slice(s, s + block)) for i, s in blocks])[permutation]


def batches_of(frames, batch_size: int, drop_last: bool = False) -> Iterator:
    for b in range(0, len(frames), batch_size):
        batch = frames[b : b + batch_size]
        if len(batch) < batch_size and drop_last:
            continue
        yield batch


def iter_frame_batches(
    store: RolloutStore,
    episodes: list[int],
    batch_size: int,
    rng: np.random.Generator,
    block: int = 32,
    buffer_blocks: int = 16,
    drop_last: bool = False,
) -> Iterator[np.ndarray]:
    """Stream shuffled frame batches: random contiguous blocks pooled in a small shuffle buffer (``frame_pools``).

    Memory is bounded by ``buffer_blocks * block`` frames whatever the dataset size (hardmaru's loader held
    the whole dataset in RAM and ran out of memory for users).
    """
    for pool in frame_pools(store, episodes, rng, block, buffer_blocks):
        yield from batches_of(read_pool(store, pool, block), batch_size, drop_last)


class _Pools:
    """``frame_pools`` as a torch map-style dataset: item k is pool k's frames, as a uint8 tensor. Each loader
    worker opens its own HDF5 handles (``RolloutStore`` drops inherited ones)."""

    def __init__(self, store: RolloutStore, pools: list, block: int):
        self.store, self.pools, self.block = store, pools, block

    def __len__(self) -> int:
        return len(self.pools)

    def __getitem__(self, k: int):
        import torch

        return torch.from_numpy(read_pool(self.store, self.pools[k], self.block))


def loaded_frame_batches(
    store: RolloutStore,
    episodes: list[int],
    batch_size: int,
    rng: np.random.Generator,
    workers: int,
    pin_memory: bool,
    block: int = 32,
    buffer_blocks: int = 16,
    drop_last: bool = False,
) -> Iterator:
    """``iter_frame_batches``'s batches, the same frames in the same order, as uint8 tensors read ahead by
    ``workers`` processes of a torch ``DataLoader`` (in page-locked memory with ``pin_memory``, so that copies to a
    GPU overlap its work). Only the reading is parallel: the shuffle is drawn here, before any worker starts."""
    import torch
    from torch.utils.data import DataLoader

    pools = _Pools(store, frame_pools(store, episodes, rng, block, buffer_blocks), block)
    # its own generator: the loader draws its workers' seeds from it, and from the global one (which the VAE's
    # sampling reads) without it
    loader = DataLoader(
        pools,
        batch_size=None,
        shuffle=False,
        num_workers=workers,
        pin_memory=pin_memory,
        generator=torch.Generator(),
    )
    for frames in loader:
        yield from batches_of(frames, batch_size, drop_last)


# ----------------------------------------------------------------------------- CLI
def validate(root: Path) -> tuple[int, int]:
    """Check every shard of a rollout directory; raises CorruptDataError naming the first bad file. Returns the
    number of recorded episodes (branched ones not counted) and of frames (all)."""
    root = Path(root)
    if not root.is_dir():
        raise CorruptDataError(f"{root} is not a directory")
    frames = 0
    for path in sorted(root.glob(SHARD_GLOB)):
        ids = check_shard(path, full=True)
        with h5py.File(path, "r") as f:
            frames += sum(f[episode_key(i)]["seg"].shape[0] for i in ids)
    store = RolloutStore(root, check=False)  # manifest and episode coverage
    store.close()
    return len(store.location) - len(store.branch_of), frames


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m worldmodel.data", description="Rollout store tools")
    sub = ap.add_subparsers(dest="cmd", required=True)
    v = sub.add_parser("validate", help="check every shard of data/NAME/rollouts")
    v.add_argument("root", type=Path)
    args = ap.parse_args(argv)
    try:
        episodes, frames = validate(args.root)
    except (CorruptDataError, FileNotFoundError) as err:
        print(f"INVALID: {err}", file=sys.stderr)
        return 1
    print(f"OK: {args.root} holds {episodes} episodes, {frames} frames, schema v{SCHEMA_VERSION}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
