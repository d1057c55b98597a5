"""A family's counterfactual labels on disk: episodes labelled in shards of ``SHARD``, each an ``.npz`` written
atomically, so that a stopped labelling resumes at the first shard missing and the labels are the same whether
or not it stopped. Used by the peer families' counterfactual-cost learners (``families/kim/counterfactual.py``,
``families/merola/counterfactual.py``); the camera family's labels, which hold frames, are HDF5
(``counterfactual_labels.py``)."""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .common import StageError, atomic_output

SHARD = 25  # labelled episodes per file


def _shard_holds(path: Path, first: int, stop: int) -> bool:
    try:
        with np.load(path) as f:
            return f["episodes"].tolist() == [first, stop]
    except (OSError, KeyError, ValueError):
        return False  # unreadable or unfinished: labelled again


def label_parts(parts: Sequence[dict], first: int, keys: Sequence[str]) -> dict:
    """Episodes ``first``, ``first + 1``, ... labelled (``label_episode``'s dicts) as one shard: ``keys`` joined,
    each decision's ``episode`` and the shard's ``episodes`` [first, stop)."""
    out = {k: np.concatenate([p[k] for p in parts]) for k in keys}
    out["episode"] = np.concatenate([np.full(len(p["t"]), first + i, np.int32) for i, p in enumerate(parts)])
    out["episodes"] = np.array([first, first + len(parts)])
    return out


def shard_labels(
    directory: Path,
    n: int,
    label_shard: Callable[[int, int], dict] | None,
    keys: Sequence[str],
    what: str,
    settings: dict | None = None,
    stop=None,
) -> dict | None:
    """``n`` labelled episodes in ``directory``: the shards missing are labelled by ``label_shard(first, stop)``
    (None: they cannot be, as when an earlier actor of the run drove them) and the whole read back, ``keys`` and
    ``episode`` joined. ``settings``: written beside them once, to say what they depend on. None when ``stop`` was
    requested before they were all labelled."""
    directory.mkdir(parents=True, exist_ok=True)
    meta = directory / "settings.json"
    if settings is not None and not meta.exists():
        meta.write_text(json.dumps(settings, default=str))
    bounds = [(k * SHARD, min((k + 1) * SHARD, n)) for k in range(math.ceil(n / SHARD))]
    paths = [directory / f"shard_{k:04d}.npz" for k in range(len(bounds))]
    todo = [k for k, p in enumerate(paths) if not _shard_holds(p, *bounds[k])]
    if todo and label_shard is None:
        raise StageError(
            f"{directory} misses {len(todo)} shards of labels that an earlier actor of this run drove: delete "
            f"{directory.parent.parent} to train the run again"
        )
    with tqdm(total=n, initial=n - sum(b - a for a, b in (bounds[k] for k in todo)), unit="episode") as bar:
        bar.set_description(what)
        for k in todo:
            if stop is not None and stop.requested:
                return None
            data = label_shard(*bounds[k])
            with atomic_output(paths[k]) as tmp, open(tmp, "wb") as fh:  # np.savez would add .npz to a name
                np.savez(fh, **data)
            bar.update(bounds[k][1] - bounds[k][0])
    parts = [dict(np.load(p)) for p in paths]
    return {k: np.concatenate([p[k] for p in parts]) for k in (*keys, "episode")}
