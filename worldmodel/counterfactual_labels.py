"""The counterfactual-cost actor's labels (docs/design.md §5): episodes driven by braking (round 0) or by the actor
(its DAgger rounds), and at each decision the exact R2 cost of every proposed shift, re-simulated; written in HDF5
shards, resumable, the same for any worker count. ``worldmodel/counterfactual.py`` fits the critic and the actor on
them."""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path

import h5py
import numpy as np
import torch
from tqdm import tqdm

from envs.counterfactual import ShiftPolicy, brake_decision, label_episode
from envs.streams import COUNTERFACTUAL_LABEL_EPISODES

from . import artifacts, loading
from .common import StageError, atomic_output, make_env, read_shards, resolve_workers, set_threads, worker_pool
from .models.counterfactual import ShiftActor, actor_from_state, features
from .recording import view_settings

log = logging.getLogger(__name__)
SHARD = 25  # labelled episodes per file
HELD_OUT = 0.15  # share of each round's labelled episodes held out, to measure the critic
FRAME_KEYS = ("seg", "speed", "action")  # per frame, up to the last decision
DECISION_KEYS = ("t", "u", "costs", "static", "chosen", "state")  # per decision


def cfg_counterfactual(cfg):
    from omegaconf import OmegaConf

    from .config import CounterfactualConfig

    return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(CounterfactualConfig), cfg.agent.counterfactual))


def label_seed(cfg) -> int:
    seed = cfg.agent.counterfactual.get("label_seed")
    return cfg.seed if seed is None else seed


def labels_dir(cfg, round_: int, run_dir: Path | None = None) -> Path:
    """Round 0: ``data/NAME/counterfactual_labels/<hash of the label settings>-seed<S>/`` (braking's states, shared
    by every run with those settings). Later rounds: ``<run>/labels/round<r>/``, since the actor drives them."""
    if round_ > 0:
        return Path(run_dir) / "labels" / f"round{round_}"
    settings = {**cfg_counterfactual(cfg).label_settings(cfg.env.step_s), **view_settings(cfg.env)}
    return (
        artifacts.data_dir(cfg)
        / "counterfactual_labels"
        / f"{artifacts.config_sha256(settings)[:10]}-seed{label_seed(cfg)}"
    )


def label_scenario(seed: int, round_: int, episode: int, c):
    from envs import sample_focus_scenario

    rng = np.random.default_rng([int(seed), COUNTERFACTUAL_LABEL_EPISODES, int(round_), int(episode)])
    return sample_focus_scenario(rng, c.hazard_share, tuple(c.speed_range), tuple(c.ttc_range)), rng


def proposer(rng: np.random.Generator, c):
    """The shifts labelled at a decision: the policy's choice, braking, ``local_share`` of the rest near the
    choice and the others uniform over [-1, 1]^3."""

    def propose(d: int, chosen: np.ndarray) -> np.ndarray:
        chosen = np.asarray(chosen, np.float32).reshape(1, 3)
        head = chosen if not chosen.any() else np.concatenate([chosen, np.zeros((1, 3), np.float32)])
        rest = c.proposals - len(head)
        local = int(round(rest * c.local_share))
        near = np.clip(chosen + rng.normal(0.0, c.local_std, (local, 3)), -1.0, 1.0)
        far = rng.uniform(-1.0, 1.0, (rest - local, 3))
        return np.concatenate([head, near, far]).astype(np.float32)[: c.proposals]

    return propose


def shift_policy(c, step_s: float, decide=brake_decision, encoder=None, name: str = "counterfactual") -> ShiftPolicy:
    """The decision structure of config ``c``: braking's by default, or ``decide(x, d)`` on the world model's view
    ``encoder`` (which then sees every frame up to the last decision)."""
    return ShiftPolicy(
        c.space(step_s),
        decide,
        c.decisions,
        c.interval(step_s),
        name=name,
        encode=None if encoder is None else encoder.encode,
        note_action=None if encoder is None else encoder.note_action,
        reset_view=None if encoder is None else encoder.reset,
    )


def actor_decision(actor: ShiftActor, decisions: int):
    """``decide(x, d)`` of a trained actor on the world model's view ``x``."""

    def decide(x: np.ndarray, d: int) -> np.ndarray:
        inp = features(np.asarray(x, np.float32)[None], np.array([d]), decisions)
        with torch.inference_mode():
            return actor(torch.from_numpy(inp).to(actor.norm.mean.device))[0].cpu().numpy()

    return decide


def _label_shard(task) -> int:
    """Worker: label the episodes of one shard (driven by braking, or by the actor in ``actor_state``) and write
    it atomically."""
    cfg_dict, round_, shard, path, n, actor_state = task
    from omegaconf import OmegaConf

    cfg = OmegaConf.create(cfg_dict)
    c = cfg_counterfactual(cfg)
    step_s = cfg.env.step_s
    env = make_env(cfg, camera=True)
    twin = env.planning_twin()
    if actor_state is None:
        policy = shift_policy(c, step_s)
    else:
        set_threads(1)
        if actor_state.get("obs") == "privileged":
            from .agent_obs import PrivilegedEncoder

            encoder = PrivilegedEncoder(env)
        else:
            encoder = loading.load_world_model(cfg)
        actor = actor_from_state(actor_state)
        policy = shift_policy(c, step_s, actor_decision(actor, c.decisions), encoder)
    parts = []
    first, stop = shard * SHARD, min((shard + 1) * SHARD, n)
    for e in range(first, stop):
        spec, rng = label_scenario(label_seed(cfg), round_, e, c)
        lab = label_episode(env, spec, policy, proposer(rng, c), c.continuations(step_s), twin)
        parts.append(lab)
    env.close()
    with atomic_output(Path(path)) as tmp, h5py.File(tmp, "w") as f:
        for key in FRAME_KEYS + DECISION_KEYS:
            f.create_dataset(key, data=np.concatenate([p[key] for p in parts]), compression="gzip")
        f.create_dataset(
            "frame_episode",
            data=np.concatenate([np.full(len(p["speed"]), e, np.int32) for e, p in zip(range(first, stop), parts)]),
        )
        f.create_dataset(
            "episode",
            data=np.concatenate([np.full(len(p["t"]), e, np.int32) for e, p in zip(range(first, stop), parts)]),
        )
        f.attrs["episodes"] = [first, stop]
    return shard


def _shard_holds(path: Path, first: int, stop: int) -> bool:
    try:
        with h5py.File(path, "r") as f:
            return [int(x) for x in f.attrs["episodes"]] == [first, stop]
    except (OSError, KeyError):
        return False  # unreadable or unfinished: labelled again


def labels(cfg, round_: int, n: int, directory: Path, actor_state: dict | None = None, stop=None) -> dict | None:
    """Round ``round_``'s ``n`` labelled episodes in ``directory``, labelling what is missing (driven by braking,
    or by the actor of ``actor_state``). None when ``stop`` was requested before they were all labelled."""
    c = cfg_counterfactual(cfg)
    directory.mkdir(parents=True, exist_ok=True)
    meta = directory / "settings.json"
    if not meta.exists():
        meta.write_text(json.dumps({**c.label_settings(cfg.env.step_s), "seed": label_seed(cfg), "round": round_}))
    paths = [directory / f"shard_{k:04d}.h5" for k in range(math.ceil(n / SHARD))]
    todo = [k for k, p in enumerate(paths) if not _shard_holds(p, k * SHARD, min((k + 1) * SHARD, n))]
    if todo and round_ > 0 and actor_state is None:
        raise StageError(
            f"{directory} misses {len(todo)} shards of labels that an earlier actor of this run drove: delete "
            f"{directory.parent.parent} to train the run again"
        )
    if todo:
        from omegaconf import OmegaConf

        cfg_dict = OmegaConf.to_container(cfg, resolve=True)
        tasks = [(cfg_dict, round_, k, str(paths[k]), n, actor_state) for k in todo]
        t0 = time.perf_counter()
        total = sum(min(SHARD, n - k * SHARD) for k in todo)
        with tqdm(total=total, desc=f"counterfactual labels (round {round_})", unit="episode") as bar:
            workers = min(resolve_workers(c.num_workers), len(tasks))
            if workers <= 1:
                for task in tasks:
                    k = _label_shard(task)
                    bar.update(min(SHARD, n - k * SHARD))
                    if stop is not None and stop.requested:
                        return None
            else:
                with worker_pool(workers) as pool:
                    for k in pool.imap_unordered(_label_shard, tasks):
                        bar.update(min(SHARD, n - k * SHARD))
        log.info(
            "[counterfactual] labelled %d shards of round %d in %.0f s", len(todo), round_, time.perf_counter() - t0
        )
    return read_shards(paths, (*FRAME_KEYS, *DECISION_KEYS, "frame_episode", "episode"))


def encode_states(encoder, data: dict, decisions: int) -> np.ndarray:
    """Every labelled decision state as a live run's world model sees it (the frames before it fed with the actions
    the driving policy took): ``features`` of shape (decisions labelled, encoder.dim + 1)."""
    from .agent_obs import encode_episode

    out = np.empty((len(data["t"]), encoder.dim), np.float32)
    d = np.empty(len(data["t"]), np.int64)
    for e in tqdm(np.unique(data["episode"]), desc="encode labelled states", unit="episode", leave=False):
        frames = np.flatnonzero(data["frame_episode"] == e)
        rows = np.flatnonzero(data["episode"] == e)
        encoded = encode_episode(encoder, data["seg"][frames], data["speed"][frames], data["action"][frames])
        out[rows] = encoded[data["t"][rows]]
        d[rows] = np.arange(len(rows))
    return features(out, d, decisions)


def privileged_states(data: dict, decisions: int) -> np.ndarray:
    """Every labelled decision state as ``obs=privileged`` sees it: the true state recorded there."""
    d = np.empty(len(data["t"]), np.int64)
    for e in np.unique(data["episode"]):
        rows = np.flatnonzero(data["episode"] == e)
        d[rows] = np.arange(len(rows))
    return features(data["state"], d, decisions)


def held_out_rows(episode: np.ndarray) -> np.ndarray:
    """True for the decisions of the last ``HELD_OUT`` share of a round's labelled episodes."""
    episodes = np.unique(episode)
    return np.isin(episode, episodes[int(round(len(episodes) * (1 - HELD_OUT))) :])
