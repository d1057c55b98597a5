"""Recording episodes to the HDF5 rollout store: the machinery the collection and the demonstrations share.

A dataset is defined by a JSON-able ``settings`` dict and two module-level functions (picklable, so spawned
workers can use them): ``spec_of(settings, index)`` gives episode ``index``'s scenario and ``policy_of(settings,
spec)`` the policy that drives it. Episode i depends only on (settings, i), so a dataset is identical whatever the
worker count. Shards appear only when complete; after a kill, ``resume=true`` writes exactly the missing shards.
``collect_config.json`` holds the settings (a resume with others is refused), ``split.json`` the seeded
train/validation split and ``manifest.json``, written last, marks the dataset complete (docs/design.md §4).
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from envs.streams import DATASET_SPLIT, RECORDING_BRANCHES

from .common import StageError, atomic_write_text, clean_temporaries, file_sha256, worker_pool, writer_lock
from .config.data import EnvConfig
from .data import SCHEMA_VERSION, shard_name, write_shard

log = logging.getLogger(__name__)

# The env settings that shape the recorded frames; the rest of the env section (horizons, camera) is the dataset's.
ENV_KEYS = ("image_size", "fov_deg", "mu", "occupants_per_car")
# The view's keys (conf/view/): they shape the frames too, and join a store's settings only when on, so that the
# paper's view keeps the names of the stores recorded before views existed.
VIEW_OFF = {key: EnvConfig.ADDED_OFF[key] for key in ("road_user_cover", "supersample")}
_ENV = None
_ENV_KWARGS: dict | None = None


def env_settings(typed) -> dict:
    """The ``ENV_KEYS`` of the typed config's ``env`` (``validate(cfg)``), and its view's keys where they are on."""
    return {**{key: getattr(typed.env, key) for key in ENV_KEYS}, **view_settings(typed.env)}


def view_env(name: str) -> dict:
    """The env keywords of the view ``conf/view/NAME.yaml`` that differ from the paper's view (for the benchmarks
    and experiments that build envs directly)."""
    from .config import compose

    return view_settings(compose("collect", ["experiment=views", f"view={name}"]).env)


def view_settings(env) -> dict:
    """The view keys of an ``env`` config section (typed or not) that differ from the paper's view."""
    values = {key: getattr(env, key, off) for key, off in VIEW_OFF.items()}
    return {key: value for key, value in values.items() if value != VIEW_OFF[key]}


def _worker_env(settings: dict):
    """One camera env per process, built from ``settings["env"]`` and the horizons in ``settings``; rebuilt when a
    dataset with other settings is recorded in the same process (the tests record several)."""
    global _ENV, _ENV_KWARGS
    kwargs = {
        "camera": True,
        "horizon_after_ttc_s": settings.get("horizon_after_ttc_s"),
        "max_episode_s": settings["max_episode_s"],
        **settings["env"],
    }
    if _ENV is None or kwargs != _ENV_KWARGS:
        from envs import UrbanCollisionEnv

        if _ENV is not None:
            _ENV.close()
        _ENV, _ENV_KWARGS = UrbanCollisionEnv(**kwargs), kwargs
    return _ENV


def _episode_arrays(seg, speed, action, r1, r2) -> dict:
    """Recorded lists -> the store's arrays: ``action[t]`` follows ``seg[t]``, the last row is padding."""
    n = len(seg)
    done = np.zeros(n, np.uint8)
    done[-2:] = 1
    pad = np.zeros((1, 2), np.float32)
    return {
        "n_steps": n - 1,
        "seg": np.stack(seg).astype(np.uint8),
        "speed": np.asarray(speed, np.float32),
        "action": np.concatenate([np.asarray(action, np.float32).reshape(-1, 2), pad]),
        "reward_r1": np.asarray(list(r1) + [0.0], np.float32),
        "reward_r2": np.asarray(list(r2) + [0.0], np.float32),
        "done": done,
    }


def record_episode(env, policy, spec, index: int, snapshot_at: int | None = None) -> dict:
    """Drive ``policy`` through ``spec`` and return the episode in the store's layout (``data.write_shard``).
    With ``snapshot_at`` = t, the env's state after step t (when the episode is still running) is kept in
    ``_snapshot`` for branching."""
    from envs.rollout import rollout

    seg, speed, action, r1, r2 = [], [], [], [], []
    kept = {}

    def first(obs, info):
        seg.append(obs["seg"])
        speed.append(obs["speed"][0])

    def record(obs, a, reward, info):
        action.append(a)
        r1.append(info["reward_r1"])
        r2.append(info["reward_r2"])
        seg.append(obs["seg"])
        speed.append(obs["speed"][0])
        if len(action) == snapshot_at and "outcome" not in info:
            kept["snapshot"] = env.snapshot()

    episode = rollout(env, policy, spec, on_step=record, on_reset=first)
    return {
        "index": index,
        "seed": spec.seed,
        "terminated": episode.terminated,
        "scenario": spec.to_json(),
        "outcome": json.dumps(episode.outcome, sort_keys=True),
        **_episode_arrays(seg, speed, action, r1, r2),
        "_outcome": episode.outcome,
        "_hazard": spec.hazard,
        "_snapshot": kept.get("snapshot"),
    }


def branch_plan(settings: dict, index: int) -> tuple[int, np.ndarray] | None:
    """Whether episode ``index`` branches, and if so (its branch step, the constant actions ``(actions, 2)``):
    a function of the settings and the index only, like everything else in a dataset."""
    b = settings.get("branch")
    if not b:
        return None
    rng = np.random.default_rng([int(settings["seed"]), int(index), RECORDING_BRANCHES])
    if rng.random() >= float(b["share"]):
        return None
    step = int(rng.integers(1, int(b["latest_step"]) + 1))
    return step, rng.uniform(-1.0, 1.0, (int(b["actions"]), 2)).astype(np.float32)


def branch_episodes(env, parent: dict, step: int, actions: np.ndarray, settings: dict) -> list[dict]:
    """The continuations of ``parent`` from the snapshot after its ``step``, one per constant action: each is
    the parent's last ``context`` frames up to the branch point, then up to ``branch.steps`` new steps."""
    b = settings["branch"]
    lo = max(0, step - int(b["context"]))
    out = []
    for j, a in enumerate(actions):
        env.restore(parent["_snapshot"])
        seg, speed = list(parent["seg"][lo : step + 1]), list(parent["speed"][lo : step + 1])
        action = list(parent["action"][lo:step])
        r1, r2 = list(parent["reward_r1"][lo:step]), list(parent["reward_r2"][lo:step])
        terminated = False
        for _ in range(int(b["steps"])):
            obs, _, terminated, truncated, info = env.step(a)
            action.append(a)
            r1.append(info["reward_r1"])
            r2.append(info["reward_r2"])
            seg.append(obs["seg"])
            speed.append(obs["speed"][0])
            if terminated or truncated:
                break
        out.append(
            {
                "index": int(settings["episodes"]) + int(parent["index"]) * int(b["actions"]) + j,
                "seed": parent["seed"],
                "terminated": bool(terminated),
                "scenario": parent["scenario"],
                "outcome": json.dumps(env.outcome(), sort_keys=True),
                **_episode_arrays(seg, speed, action, r1, r2),
                "branch_of": int(parent["index"]),
                "branch_step": int(step),
            }
        )
    return out


def record_shard(task: tuple) -> dict:
    """Record the episodes of one shard and write it atomically; returns its statistics."""
    settings, root, k, indices, spec_of, policy_of = task
    env = _worker_env(settings)
    episodes, branches = [], []
    for i in indices:
        spec = spec_of(settings, i)
        plan = branch_plan(settings, i)
        episode = record_episode(env, policy_of(settings, spec), spec, i, snapshot_at=plan[0] if plan else None)
        episodes.append(episode)
        if episode["_snapshot"] is not None:
            branches += branch_episodes(env, episode, plan[0], plan[1], settings)
    meta = {
        "class_names": json.dumps(__import__("envs").CLASS_NAMES),
        "dt": 1.0 / 15.0,
        "settings": json.dumps(settings, sort_keys=True),
    }
    write_shard(Path(root) / shard_name(k), episodes + branches, meta)
    return {
        "shard": k,
        "lengths": {e["index"]: len(e["seg"]) for e in episodes + branches},
        "branches": {e["index"]: e["branch_of"] for e in branches},
        "hazards": [e["_hazard"] for e in episodes],
        "outcomes": [e["_outcome"] for e in episodes],
    }


def split_episodes(seed: int, episodes: int, fraction: float) -> dict:
    order = np.random.default_rng([seed, DATASET_SPLIT]).permutation(episodes)
    n_val = max(1, int(round(fraction * episodes))) if episodes > 1 else 0
    return {"train": sorted(int(i) for i in order[n_val:]), "validation": sorted(int(i) for i in order[:n_val])}


def record_dataset(root: Path, settings: dict, *args, label: str, **kwargs) -> dict:
    """Write (or finish, or confirm) the dataset ``settings`` defines under ``root``, holding its writer lock;
    returns its summary. The rest of the arguments are ``_record_dataset``'s."""
    check_room(root, settings["episodes"], "demos.episodes" if label == "demonstrate" else "collect.episodes")
    with writer_lock(root, "one dataset"):
        return _record_dataset(root, settings, *args, label=label, **kwargs)


def _check_existing(root: Path, settings: dict, resume: bool, label: str) -> dict | None:
    """What is already in ``root``: the summary of a complete dataset with nothing to do, None to record (after
    setting damaged shards aside), or a StageError when it was recorded otherwise or may not be extended."""
    manifest_path = root / "manifest.json"
    config_path = root / "collect_config.json"
    previous = json.loads(config_path.read_text())
    if previous.get("schema_version") != settings.get("schema_version"):
        raise StageError(
            f"{root} was recorded with data schema version {previous.get('schema_version')}, and this code "
            f"writes version {settings.get('schema_version')} (data/README.md says what changed). The stages "
            f"still read it, but it cannot be extended: use another experiment=NAME, or delete {root} to "
            "recollect it."
        )
    if previous != settings:
        raise StageError(
            f"{root} was recorded with different settings ({config_path}). Use another "
            f"experiment=NAME, or delete {root} to start again."
        )
    if manifest_path.exists():
        manifest = json.loads(manifest_path.read_text())
        damaged = damaged_shards(root, manifest)
        if not damaged:
            log.info("[%s] %s is already complete; nothing to do.", label, root)
            return manifest["summary"]
        if not resume:
            raise StageError(
                f"{root} is complete, but shards {', '.join(damaged)} are missing, truncated or changed. Pass "
                "resume=true to record them again (the same episodes from the same seeds; the damaged files "
                f"are kept in {root / DAMAGED})."
            )
        set_aside(root, damaged)
        log.warning("[%s] %s: recording shards %s again", label, root, ", ".join(damaged))
    elif not resume:
        raise StageError(f"{root} holds a partial dataset. Pass resume=true to finish it, or delete it.")
    return None


def _record_dataset(
    root: Path,
    settings: dict,
    spec_of: Callable,
    policy_of: Callable,
    *,
    resume: bool,
    num_workers: int,
    validation_fraction: float,
    label: str,
) -> dict:
    manifest_path = root / "manifest.json"
    config_path = root / "collect_config.json"
    if config_path.exists():
        summary = _check_existing(root, settings, resume, label)
        if summary is not None:
            return summary
    root.mkdir(parents=True, exist_ok=True)
    clean_temporaries(root)
    atomic_write_text(config_path, json.dumps(settings, indent=2, sort_keys=True))
    split = split_episodes(settings["seed"], settings["episodes"], validation_fraction)
    atomic_write_text(root / "split.json", json.dumps(split))

    per = settings["episodes_per_shard"]
    shards = [
        (k, list(range(k * per, min(settings["episodes"], (k + 1) * per))))
        for k in range((settings["episodes"] + per - 1) // per)
    ]
    todo = [
        (settings, str(root), k, ids, spec_of, policy_of) for k, ids in shards if not (root / shard_name(k)).exists()
    ]
    done_stats = _stats_of_existing(root, [k for k, _ in shards if (root / shard_name(k)).exists()])

    from tqdm import tqdm

    t0 = time.perf_counter()
    workers = min(int(num_workers), max(1, len(todo)))
    new_stats = []
    done_episodes = sum(len(s["lengths"]) - len(s["branches"]) for s in done_stats)
    with tqdm(total=settings["episodes"], initial=done_episodes, unit="episode", desc=label) as bar:
        if workers == 1:
            for task in todo:
                new_stats.append(record_shard(task))
                bar.update(len(task[3]))
        else:
            with worker_pool(workers) as pool:
                for stats in pool.imap_unordered(record_shard, todo):
                    new_stats.append(stats)
                    bar.update(len(stats["lengths"]) - len(stats["branches"]))
    wall = time.perf_counter() - t0

    all_stats = done_stats + new_stats
    summary = _summarise(all_stats, wall, sum(sum(s["lengths"].values()) for s in new_stats))
    lengths = {str(i): n for s in all_stats for i, n in s["lengths"].items()}
    branches = {str(i): p for s in all_stats for i, p in sorted(s["branches"].items())}
    manifest = {
        "schema_version": SCHEMA_VERSION,
        "episodes": settings["episodes"],
        "shards": [shard_name(k) for k, _ in shards],
        "lengths": lengths,
        "branches": branches,
        "summary": summary,
        # each shard's bytes as written: a later collection with resume=true records a changed one again
        "digests": {shard_name(k): file_sha256(root / shard_name(k)) for k, _ in shards},
    }
    atomic_write_text(manifest_path, json.dumps(manifest, indent=1, sort_keys=True))
    log.info(
        "[%s] %s: %d episodes, %d frames; hazards %s; collisions %s; ended by %s; %s s wall, %s frames/s",
        label,
        root,
        summary["episodes"],
        summary["frames"],
        summary["hazards"],
        summary["collisions"],
        summary["ended_by"],
        summary["wall_s"],
        summary["frames_per_s_this_run"],
    )
    return summary


# The least an episode takes on disk: paper-scale episodes take 39 kB (94 MB for 2,400), shorter ones 20-40 kB; a
# quarter of that, so that the check refuses only what cannot fit.
EPISODE_BYTES_AT_LEAST = 10_000
SPLIT_BYTES_PER_EPISODE = 64  # the split's permutation (8 bytes) and its two sorted lists of Python ints


def check_room(root: Path, episodes: int, key: str) -> None:
    """Refuse, before anything is written or held in memory, a dataset that cannot fit on the disk under ``root``."""
    import shutil

    where = Path(root).absolute()
    while not where.exists():
        where = where.parent
    free, need = shutil.disk_usage(where).free, int(episodes) * EPISODE_BYTES_AT_LEAST
    if need > free:
        raise StageError(
            f"{key}={episodes} needs at least {need / 1e9:,.0f} GB under {root} (10 kB or more an episode), and "
            f"{free / 1e9:,.0f} GB are free there. Lower {key}, or point paths.data_root at a larger disk."
        )
    memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    if int(episodes) * SPLIT_BYTES_PER_EPISODE > memory:  # the train/validation split is drawn whole, in memory
        raise StageError(
            f"{key}={episodes} needs more memory than this machine's {memory / 1e9:,.0f} GB to draw its train/"
            f"validation split ({SPLIT_BYTES_PER_EPISODE} bytes an episode). Lower {key}."
        )


DAMAGED = "damaged"  # where a collection resumed on a complete dataset keeps the shards it records again


def damaged_shards(root: Path, manifest: dict) -> list[str]:
    """The manifest's shards that are missing or differ from what was written: by their recorded digests, or for a
    dataset recorded before digests, by a check of their structure."""
    from .data import CorruptDataError, check_shard

    digests = manifest.get("digests")
    out = []
    for name in manifest["shards"]:
        path = root / name
        if not path.exists():
            out.append(name)
        elif digests is not None:
            if file_sha256(path) != digests.get(name):
                out.append(name)
        else:
            try:
                check_shard(path, full=False)
            except CorruptDataError:
                out.append(name)
    return out


def set_aside(root: Path, names: list[str]) -> None:
    """Move damaged shards into ``root/damaged/`` (nothing is deleted): the collection then records them again."""
    for name in names:
        path = root / name
        if path.exists():
            target = root / DAMAGED / f"{name}.{time.strftime('%Y%m%d-%H%M%S')}"
            target.parent.mkdir(exist_ok=True)
            path.rename(target)


def _stats_of_existing(root: Path, ks: list[int]) -> list[dict]:
    import h5py

    from envs import ScenarioSpec

    from .data import check_shard, episode_key

    stats = []
    for k in ks:
        path = root / shard_name(k)
        ids = check_shard(path, full=False)
        with h5py.File(path, "r") as f:
            groups = [f[episode_key(i)] for i in ids]
            branches = {i: int(g.attrs["branch_of"]) for i, g in zip(ids, groups) if g.attrs.get("branch_of", -1) >= 0}
            eps = [g for i, g in zip(ids, groups) if i not in branches]
            stats.append(
                {
                    "shard": k,
                    "lengths": {i: g["seg"].shape[0] for i, g in zip(ids, groups)},
                    "branches": branches,
                    # scenario JSON -> hazard name, as a fresh run reports it
                    "hazards": [ScenarioSpec.from_dict(json.loads(g.attrs["scenario"])).hazard for g in eps],
                    "outcomes": [json.loads(g.attrs["outcome"]) for g in eps],
                }
            )
    return stats


def _summarise(stats: list[dict], wall: float, new_frames: int) -> dict:
    outcomes = [o for s in stats for o in s["outcomes"]]
    hazards = [h for s in stats for h in s["hazards"]]
    frames = sum(sum(s["lengths"].values()) for s in stats)
    branched = [i for s in stats for i in s["branches"]]
    branch_frames = sum(s["lengths"][i] for s in stats for i in s["branches"])
    return {
        "episodes": len(outcomes),
        "frames": frames,
        "branched_episodes": len(branched),
        "branch_frames": branch_frames,
        "hazards": {k: hazards.count(k) for k in ("pedestrian", "car", "both", "none")},
        "collisions": {k: int(sum(o[f"{k}_collision"] for o in outcomes)) for k in ("pedestrian", "vehicle", "static")},
        "ended_by": {k: sum(o["end"] == k for o in outcomes) for k in ("crash", "left_scene", "horizon")},
        "wall_s": round(wall, 2),
        "frames_per_s_this_run": round(new_frames / wall, 1) if wall > 0 else None,
    }
