"""The chooser's labels (``agent.learner=chooser``; docs/design.md §5): straight-line braking through
``chooser.episodes`` scenarios with the camera on, and at each decision step the exact cost of starting every
candidate manoeuvre there (the planner's re-simulation, ``envs.chooser.cost_labels``). Stored under
``data/NAME/chooser_labels/<settings>-seed<S>/`` in HDF5 shards of ``SHARD`` episodes, written atomically by
``chooser.num_workers`` processes; an interrupted labelling continues where it stopped. ``worldmodel/chooser.py``
learns from them.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import time
from pathlib import Path

import h5py
import numpy as np
from tqdm import tqdm

from envs.chooser import cost_labels, decide_steps_for
from envs.streams import CHOOSER_LABEL_EPISODES

from . import artifacts
from .common import atomic_output, make_env, read_shards, resolve_workers, worker_pool
from .recording import view_settings

log = logging.getLogger(__name__)
SHARD = 25  # labelled episodes per file
LABEL_KEYS = ("seg", "speed", "costs", "state", "episode", "t")
STATIC_KEY = "static"  # per candidate, whether it ends in a static object (older labels lack it)
TELE_KEY = "seg_tele"  # the narrow second camera's frames, in labels made with env.tele_fov_deg
SOURCES = ("train", "validation")  # training labels, or the validation bank's scenarios (for choosing settings)


def labels_dir(cfg, source: str = "train") -> Path:
    """``data/NAME/chooser_labels/<hash of the label settings>-seed<S>/`` for the training labels;
    ``.../validation-<hash>/`` for the validation bank's scenarios (independent of the training seed)."""
    settings = cfg_chooser(cfg).label_settings()
    if cfg.env.get("tele_fov_deg") is not None:  # the labels also hold the second camera's frames
        settings["tele_fov_deg"] = cfg.env.tele_fov_deg
    settings.update(view_settings(cfg.env))  # the frames' view, where it is not the paper's
    if source == "validation":
        e = cfg.evaluate
        settings = {**settings, "bank": [list(e.ttcs), list(e.speeds), list(e.hazards), e.per_cell]}
        settings["bank_seed"] = e.validation_seed
        return artifacts.data_dir(cfg) / "chooser_labels" / f"validation-{artifacts.config_sha256(settings)[:10]}"
    seed = label_seed(cfg)
    return artifacts.data_dir(cfg) / "chooser_labels" / f"{artifacts.config_sha256(settings)[:10]}-seed{seed}"


def label_seed(cfg) -> int:
    """The seed of the labelled scenarios: ``agent.chooser.label_seed``, or the training seed when that is unset."""
    seed = cfg.agent.chooser.get("label_seed")
    return cfg.seed if seed is None else seed


def validation_entries(cfg):
    """The validation bank (``evaluate.bank=validation``): the same grid and seed as evaluation draws."""
    from envs import scenario_bank

    e = cfg.evaluate
    return scenario_bank(
        ttcs=tuple(e.ttcs),
        speeds=tuple(e.speeds),
        hazards=tuple(e.hazards),
        per_cell=e.per_cell,
        seed=e.validation_seed,
    )


def cfg_chooser(cfg):
    from omegaconf import OmegaConf

    from .config import ChooserConfig

    return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(ChooserConfig), cfg.agent.chooser))


def label_scenario(seed: int, episode: int, c):
    from envs import sample_focus_scenario

    rng = np.random.default_rng([int(seed), CHOOSER_LABEL_EPISODES, int(episode)])
    return sample_focus_scenario(rng, c.hazard_share, tuple(c.speed_range), tuple(c.ttc_range))


def _label_shard(task) -> int:
    """Worker: label the episodes of one shard and write it atomically."""
    cfg_dict, shard, path, source = task
    from omegaconf import OmegaConf

    cfg = OmegaConf.create(cfg_dict)
    c = cfg_chooser(cfg)
    step_s = cfg.env.step_s
    candidates, steps = c.candidates(step_s), decide_steps_for(c.decide_s, step_s)
    env = make_env(cfg, camera=True)
    twin = env.planning_twin()
    parts = []
    bank = validation_entries(cfg) if source == "validation" else None
    first, stop = shard * SHARD, min((shard + 1) * SHARD, len(bank) if bank is not None else c.episodes)
    for e in range(first, stop):
        spec = bank[e].spec if bank is not None else label_scenario(label_seed(cfg), e, c)
        lab = cost_labels(env, spec, candidates, steps, twin)
        n = len(lab["speed"])
        parts.append({**lab, "episode": np.full(n, e, np.int32), "t": np.arange(n, dtype=np.int16)})
    env.close()
    with atomic_output(Path(path)) as tmp, h5py.File(tmp, "w") as f:
        for key in parts[0]:
            f.create_dataset(key, data=np.concatenate([p[key] for p in parts]), compression="gzip")
        f.attrs["episodes"] = [first, stop]
    return shard


def _shard_holds(path: Path, first: int, stop: int) -> bool:
    """Whether the shard at ``path`` holds the labels of episodes [first, stop). A shard labelled while another
    number of episodes was asked for holds another range, and is labelled again. (Shards from before the range was
    recorded are judged by their last episode.)"""
    try:
        with h5py.File(path, "r") as f:
            if "episodes" in f.attrs:
                return [int(x) for x in f.attrs["episodes"]] == [first, stop]
            episode = f["episode"][...]
            return len(episode) > 0 and int(episode.max()) == stop - 1
    except (OSError, KeyError):
        return True  # unreadable: reading it names the file and what to do


def labels(cfg, source: str = "train") -> dict:
    """The labelled decision states (``seg``, ``speed``, ``costs``, ``episode``, ``t``), making what is missing.
    ``source``: the training scenarios, or the validation bank's (episode = the bank entry's index)."""
    if source not in SOURCES:
        raise ValueError(f"chooser label source {source!r}: use one of {SOURCES}")
    c = cfg_chooser(cfg)
    out = labels_dir(cfg, source)
    out.mkdir(parents=True, exist_ok=True)
    settings = {**c.label_settings(), "seed": label_seed(cfg), "source": source}
    meta = out / "settings.json"
    if not meta.exists():
        meta.write_text(json.dumps(settings, indent=1))
    n = len(validation_entries(cfg)) if source == "validation" else c.episodes
    n_shards = math.ceil(n / SHARD)
    paths = [out / f"shard_{k:04d}.h5" for k in range(n_shards)]
    todo = [k for k, p in enumerate(paths) if not (p.exists() and _shard_holds(p, k * SHARD, min((k + 1) * SHARD, n)))]
    if todo:
        from omegaconf import OmegaConf

        cfg_dict = OmegaConf.to_container(cfg, resolve=True)
        tasks = [(cfg_dict, k, str(paths[k]), source) for k in todo]
        t0 = time.perf_counter()
        with tqdm(
            total=sum(min(SHARD, n - k * SHARD) for k in todo), desc=f"chooser labels ({source})", unit="episode"
        ) as bar:
            workers = min(resolve_workers(c.num_workers), len(tasks))
            if workers <= 1:
                for t in tasks:
                    k = _label_shard(t)
                    bar.update(min(SHARD, n - k * SHARD))
            else:
                with worker_pool(workers) as pool:
                    for k in pool.imap_unordered(_label_shard, tasks):
                        bar.update(min(SHARD, n - k * SHARD))
        log.info("[chooser] labelled %d shards in %s in %.0f s", len(todo), out, time.perf_counter() - t0)
    data: dict[str, list] = {k: [] for k in LABEL_KEYS}
    if cfg.env.get("tele_fov_deg") is not None:
        data[TELE_KEY] = []
    with contextlib.suppress(OSError), h5py.File(paths[0], "r") as f:
        if STATIC_KEY in f:  # labels made before the flags have none; what counts static collisions says so
            data[STATIC_KEY] = []
    return read_shards(paths, data)
