"""The counterfactual-cost actor (``agent.learner=counterfactual``; docs/design.md §5): a DDPG actor on the world
model's [z_t, zhat_{t+1}, speed] whose critic learns the exact costs the simulator gives its manoeuvres.

The paper's DDPG learns its critic by bootstrapping from sparse terminal rewards, and on this simulator it learns
to swerve without learning where swerving is safe (docs/results/agent/). Here the critic's targets are exact
instead: at each decision state the simulator re-simulates a set of shifts (``envs/counterfactual.py``: steer,
pedal and duration, with a second decision ``interval`` later) and returns the R2 cost of each. The pieces:

1. **Labels, round 0**: straight-line braking drives ``episodes`` focus-mix scenarios with the camera on; at each
   of its decisions the simulator labels ``proposals`` shifts. Stored under
   ``data/NAME/counterfactual_labels/<settings>-seed<S>/`` in HDF5 shards written atomically; an interrupted
   labelling continues where it stopped.
2. **Critic**: an ensemble of ``critic_members`` MLPs regresses the labelled cost of (state, decision, u), the
   state being the world model's view exactly as a live run feeds it.
3. **Actor**: the paper's actor network (``agent.actor_hidden``, tanh outputs u in [-1, 1]^3, its last layer at
   zero so it starts as braking) follows the critic's gradient (DDPG's actor update) to the shift it predicts
   cheapest, pessimistically (``pessimism`` x the members' spread), and anchored to braking where the members
   disagree (``anchor_weight``).
   Two options, off by default, probe where the actor's limit lies: ``critic_obs=privileged`` fits the critic on
   the true state while the actor reads the world model, and ``search`` also regresses the actor towards the
   cheapest of many shifts the critic scores per state, which no gradient step from braking may reach.
4. **DAgger rounds**: the actor drives ``dagger_episodes`` new scenarios, its own states are labelled the same way
   (its choice and shifts near it among the proposals; stored in the run folder, since they depend on its actor),
   and the critic and actor are fitted again on everything so far.

Each phase (a round's critic, then its actor) starts from its own seeds, and the checkpoint is saved after every
phase, so a run stopped anywhere resumes from its last finished phase to the same weights as an uninterrupted run.
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path

import h5py
import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from envs.counterfactual import ShiftPolicy, brake_decision, label_episode
from envs.privileged import PRIVILEGED_DIM
from envs.streams import COUNTERFACTUAL_LABEL_EPISODES, COUNTERFACTUAL_MINIBATCHES

from . import artifacts
from .action_map import ActionMap
from .common import (
    StageError,
    atomic_output,
    check_finite,
    make_env,
    read_shards,
    resolve_workers,
    seed_everything,
    set_threads,
    worker_pool,
)
from .config import validate
from .models.ddpg import Actor, mlp
from .stats import rank_agreement

log = logging.getLogger(__name__)
SHARD = 25  # labelled episodes per file
HELD_OUT = 0.15  # share of each round's labelled episodes held out, to measure the critic
FRAME_KEYS = ("seg", "speed", "action")  # per frame, up to the last decision
DECISION_KEYS = ("t", "u", "costs", "static", "chosen", "state")  # per decision
CHECK_EVERY = 500  # minibatches between held-out measurements in TensorBoard


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
    settings = cfg_counterfactual(cfg).label_settings(cfg.env.step_s)
    return (
        artifacts.data_dir(cfg)
        / "counterfactual_labels"
        / f"{artifacts.config_sha256(settings)[:10]}-seed{label_seed(cfg)}"
    )


# ----------------------------------------------------------------------------- the networks
class Normalised(nn.Module):
    """Fixed per-feature statistics of the training states (buffers, so they travel with the checkpoint)."""

    def __init__(self, in_dim: int):
        super().__init__()
        self.register_buffer("mean", torch.zeros(in_dim))
        self.register_buffer("std", torch.ones(in_dim))

    def fit(self, x: torch.Tensor) -> None:
        self.mean.copy_(x.mean(0))
        self.std.copy_(x.std(0).clamp_min(1e-2))  # a feature constant in training stays 0

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std


class CostCritic(nn.Module):
    """(state features, u) -> every member's predicted R2 cost, shape (members, batch). Each member reads the state
    through a first layer of its own, and u joins after it; a linear head on that layer guesses the true state
    (``envs.privileged``), a training target only (``aux``)."""

    def __init__(self, in_dim: int, members: int, hidden, aux_dim: int = PRIVILEGED_DIM):
        super().__init__()
        hidden = [int(h) for h in hidden]
        self.norm = Normalised(in_dim)
        self.trunks = nn.ModuleList(nn.Sequential(nn.Linear(in_dim, hidden[0]), nn.ReLU()) for _ in range(members))
        self.heads = nn.ModuleList(mlp(hidden[0] + 3, hidden[1:], 1) for _ in range(int(members)))
        self.aux = nn.ModuleList(nn.Linear(hidden[0], aux_dim) for _ in range(int(members)))

    def member(self, m: int, x: torch.Tensor, u: torch.Tensor, aux: bool = False):
        h = self.trunks[m](self.norm(x))
        out = self.heads[m](torch.cat([h, u], dim=1))[:, 0]
        return (out, self.aux[m](h)) if aux else out

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return torch.stack([self.member(m, x, u) for m in range(len(self.heads))])

    def grid(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Every member's cost of each state's ``k`` shifts ``u`` (batch, k, 3): (members, batch, k). Each state's
        first layer is computed once, not once per shift."""
        x = self.norm(x)
        out = []
        for trunk, head in zip(self.trunks, self.heads, strict=True):
            h = trunk(x)[:, None].expand(-1, u.shape[1], -1)
            out.append(head(torch.cat([h, u], dim=2))[..., 0])
        return torch.stack(out)


class ShiftActor(nn.Module):
    """The paper's actor network (``models.ddpg.Actor``) on the normalised state features: u in [-1, 1]^3, braking
    at initialisation. A linear head on its first hidden layer guesses the true state (``aux``; training only)."""

    def __init__(self, in_dim: int, hidden, aux_dim: int = PRIVILEGED_DIM):
        super().__init__()
        self.norm = Normalised(in_dim)
        self.actor = Actor(in_dim, 3, tuple(int(h) for h in hidden), final_bound=0.0)
        self.aux = nn.Linear(int(hidden[0]), aux_dim)

    def forward(self, x: torch.Tensor, aux: bool = False):
        net = self.actor.net
        h = net[1](net[0](self.norm(x)))
        u = torch.tanh(net[2:](h))
        return (u, self.aux(h)) if aux else u


def features(encoded: np.ndarray, d: np.ndarray, decisions: int) -> np.ndarray:
    """The learner's state: the world model's view, then the decision's index as a share of the decisions."""
    return np.concatenate([encoded, (np.asarray(d, np.float32) / decisions)[:, None]], axis=1).astype(np.float32)


# ----------------------------------------------------------------------------- labels
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
            encoder = artifacts.load_world_model(cfg)
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


# ----------------------------------------------------------------------------- fitting
def pairwise_order(pred: np.ndarray, costs: np.ndarray) -> float:
    """Over every decision state and every pair of its shifts whose exact costs differ, the share that ``pred``
    orders as the costs do (``stats.rank_agreement``): 0.5 for any constant predictor, 1 for a perfect one."""
    a = rank_agreement(pred, costs)
    return float(a["agree"].sum() / a["pairs"].sum()) if a["pairs"].sum() else float("nan")


def rank_correlation(pred: np.ndarray, costs: np.ndarray) -> float:
    """The mean over decision states of Spearman's rank correlation between ``pred`` and the exact costs of that
    state's shifts (states whose shifts all cost the same are left out)."""
    rho = rank_agreement(pred, costs)["spearman"]
    return float(np.nanmean(rho)) if np.isfinite(rho).any() else float("nan")


def critic_predict(critic: CostCritic, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The critic's mean prediction for every state's proposals: x (S, F), u (S, N, 3) -> (S, N)."""
    s, n = u.shape[:2]
    with torch.no_grad():
        xt = torch.from_numpy(np.repeat(x, n, axis=0))
        return critic(xt, torch.from_numpy(u.reshape(-1, 3))).mean(0).reshape(s, n).numpy()


def phase_seed(seed: int, round_: int, phase: int) -> int:
    return int(np.random.default_rng([int(seed), COUNTERFACTUAL_MINIBATCHES, round_, phase]).integers(2**31 - 1))


def fit_critic(x, u, costs, state, held, c, seed: int, round_: int, run_=None, log_from: int = 0):
    """A fresh ensemble fitted to the labelled costs of the training rows (``held`` False), its state heads to the
    true ``state`` with weight ``c.aux_weight``. Returns (critic,
    held-out figures), or (None, None) when ``run_`` (a ``TrainingRun``: TensorBoard, stop; None: neither) was asked
    to stop."""
    writer, stop, last = (run_.writer, run_.stop, run_.last) if run_ is not None else (None, None, None)
    torch.manual_seed(phase_seed(seed, round_, 0))
    rng = np.random.default_rng(phase_seed(seed, round_, 0))
    critic = CostCritic(x.shape[1], c.critic_members, c.critic_hidden)
    xt, ut, yt, st = (torch.from_numpy(a[~held]) for a in (x, u, costs, state))
    critic.norm.fit(xt)
    opt = torch.optim.AdamW(critic.parameters(), lr=c.critic_lr, weight_decay=c.weight_decay)
    n_states, n_prop = yt.shape
    for k in tqdm(range(c.critic_steps), desc=f"critic (round {round_})", unit="batch", leave=False, disable=not run_):
        loss = 0.0
        for m in range(c.critic_members):
            i = torch.from_numpy(rng.integers(0, n_states, c.batch_size))
            j = torch.from_numpy(rng.integers(0, n_prop, c.batch_size))
            pred, guess = critic.member(m, xt[i], ut[i, j], aux=True)
            loss = loss + ((pred - yt[i, j]) ** 2).mean() + c.aux_weight * ((guess - st[i]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if k % 50 == 0:
            value = loss.item() / c.critic_members
            check_finite(value, "critic loss", k, last)
            if writer is not None:
                writer.add_scalar("critic/train_mse", value, log_from + k)
        if writer is not None and ((k + 1) % CHECK_EVERY == 0 or k + 1 == c.critic_steps):
            figures = critic_figures(critic, x[held], u[held], costs[held])
            for name, value in figures.items():
                writer.add_scalar(f"critic/held_out_{name}", value, log_from + k)
        if stop is not None and stop.requested:
            return None, None
    return critic.eval(), critic_figures(critic.eval(), x[held], u[held], costs[held])


def critic_figures(critic: CostCritic, x, u, costs) -> dict:
    """How well the critic knows the held-out labelled costs: mean squared error, pairwise order and Spearman."""
    if not len(x):
        return {}
    pred = critic_predict(critic, x, u)
    return {
        "mse": float(((pred - costs) ** 2).mean()),
        "pairwise_order": pairwise_order(pred, costs),
        "spearman": rank_correlation(pred, costs),
    }


def objective(critic: CostCritic, u: torch.Tensor, x: torch.Tensor, c, scale: torch.Tensor | None = None):
    """Per state: the predicted cost of shift ``u``, pessimistic by the members' spread, plus the braking anchor
    weighted by that spread over ``scale`` (the minibatch's mean spread where None). Returns (objective, scale)."""
    return objective_of(critic(x, u), u, c, scale)


def objective_of(q: torch.Tensor, u: torch.Tensor, c, scale: torch.Tensor | None = None):
    """``objective`` from the members' predictions ``q`` (members, ...) of the shifts ``u`` (..., 3)."""
    mean, spread = q.mean(0), q.std(0) if q.shape[0] > 1 else torch.zeros_like(q[0])
    anchor = (u[..., :2] ** 2).sum(-1)
    scale = spread.mean().clamp_min(1e-6).detach() if scale is None else scale
    return mean + c.pessimism * spread + c.anchor_weight * (spread / scale).detach() * anchor, scale


def actor_loss(critic: CostCritic, u: torch.Tensor, x: torch.Tensor, c) -> torch.Tensor:
    """The minibatch's mean ``objective``: what the actor's gradient step lowers."""
    return objective(critic, u, x, c)[0].mean()


def searched_shifts(critic: CostCritic, u: torch.Tensor, x: torch.Tensor, c, generator: torch.Generator):
    """Per state, the shift of lowest ``objective`` among the actor's own ``u``, braking and ``c.search`` shifts
    drawn uniformly over [-1, 1]^3: where the critic's cheapest shift lies in another basin (a swerve to the other
    side, say) than the actor's, a gradient step cannot reach it, and a regression towards it can."""
    with torch.no_grad():
        own, scale = objective(critic, u, x, c)
        n, k = len(u), int(c.search)
        drawn = torch.rand(n, k, 3, generator=generator) * 2.0 - 1.0
        candidates = torch.cat([u[:, None], torch.zeros_like(u)[:, None], drawn], dim=1)  # (n, k + 2, 3)
        values = objective_of(critic.grid(x, candidates), candidates, c, scale)[0]
        values[:, 0] = own  # the actor's own, exactly as its loss scores it
        return candidates[torch.arange(n), values.argmin(1)]


def fit_actor(
    actor: ShiftActor, critic: CostCritic, x, xc, state, held, c, seed: int, round_: int, run_=None, log_from=0
):
    """The actor trained on the training states against the frozen critic, its state head to the true ``state``
    with weight ``c.aux_weight``; the actor reads ``x``, the critic the same states as ``xc`` (its own view,
    ``critic_obs``). Returns held-out figures, or None when
    ``run_`` (a ``TrainingRun``: TensorBoard, stop; None: neither) was asked to stop."""
    writer, stop, last = (run_.writer, run_.stop, run_.last) if run_ is not None else (None, None, None)
    torch.manual_seed(phase_seed(seed, round_, 1))
    rng = np.random.default_rng(phase_seed(seed, round_, 1))
    for p in critic.parameters():
        p.requires_grad_(False)
    xt, xct, st = (torch.from_numpy(a[~held]) for a in (x, xc, state))
    if round_ == 0:
        actor.norm.fit(xt)
    opt = torch.optim.Adam(actor.parameters(), lr=c.actor_lr)
    draws = torch.Generator().manual_seed(phase_seed(seed, round_, 3))
    for k in tqdm(range(c.actor_steps), desc=f"actor (round {round_})", unit="batch", leave=False, disable=not run_):
        i = torch.from_numpy(rng.integers(0, len(xt), c.batch_size))
        u, guess = actor(xt[i], aux=True)
        loss = actor_loss(critic, u, xct[i], c) + c.aux_weight * ((guess - st[i]) ** 2).mean()
        if c.search:
            target = searched_shifts(critic, u.detach(), xct[i], c, draws)
            loss = loss + c.search_weight * ((u - target) ** 2).sum(1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if k % 50 == 0:
            check_finite(loss.item(), "actor loss", k, last)
            if writer is not None:
                writer.add_scalar("actor/loss", loss.item(), log_from + k)
        if stop is not None and stop.requested:
            return None
    figures = actor_figures(actor, critic, x[held], xc[held], c)
    for name, value in figures.items():
        if writer is not None:
            writer.add_scalar(f"actor/held_out_{name}", value, log_from + c.actor_steps - 1)
    return figures


def actor_figures(actor: ShiftActor, critic: CostCritic, x, xc, c) -> dict:
    """On held-out states (``x`` as the actor reads them, ``xc`` as the critic does): the critic's predicted cost of
    the actor's shifts and of braking, the actor's objective (``actor_loss``) against braking's, and how far the
    actor moves from braking."""
    if not len(x):
        return {}
    with torch.no_grad():
        u = actor(torch.from_numpy(x))
        xt = torch.from_numpy(xc)
        brake = torch.zeros_like(u)
        return {
            "predicted_cost": float(critic(xt, u).mean()),
            "predicted_braking_cost": float(critic(xt, brake).mean()),
            "objective": float(actor_loss(critic, u, xt, c)),
            "braking_objective": float(actor_loss(critic, brake, xt, c)),
            "steer_abs": float(u[:, 0].abs().mean()),
            "switch_share": float(((u[:, 0].abs() > 0.1) | (u[:, 1] > 0.1)).float().mean()),
        }


# ----------------------------------------------------------------------------- the stage
def actor_from_state(state: dict) -> ShiftActor:
    actor = ShiftActor(int(state["in_dim"]), state["actor_hidden"])
    actor.load_state_dict(state["actor"])
    return actor.eval()


def train(cfg, run_, agent_id) -> dict:
    """Every round's labels, critic and actor, resuming after the last finished phase; saves through ``run_``."""
    typed = validate(cfg)
    c = typed.agent.counterfactual
    step_s = typed.env.step_s
    set_threads(typed.threads)
    # the training draws from its own seeded generators only; the process-wide ones are seeded too, because the
    # checkpoint saves their state, which would otherwise be whatever ran in this process before
    seed_everything(typed.seed)
    privileged = typed.agent.obs == "privileged"  # the true state instead of the world model's view
    encoder = None if privileged else artifacts.load_world_model(cfg)
    in_dim = (PRIVILEGED_DIM if privileged else encoder.dim) + 1
    # the critic only trains the actor, so it may read the true state while the actor reads the world model's view
    critic_true_state = privileged or c.critic_obs == "privileged"
    critic_in = PRIVILEGED_DIM + 1 if critic_true_state else in_dim
    saved = run_.state or {}
    done = list(saved.get("done", []))
    torch.manual_seed(phase_seed(typed.seed, 0, 2))  # the actor's initial weights (its last layer is zero)
    actor = ShiftActor(in_dim, typed.agent.actor_hidden)
    critic = None
    if "actor" in saved:
        actor.load_state_dict(saved["actor"])
    if saved.get("critic") is not None:
        critic = CostCritic(critic_in, c.critic_members, c.critic_hidden)
        critic.load_state_dict(saved["critic"])
    history = dict(saved.get("history", {}))
    if done:
        run_.resumed(f"after {done[-1]}")
    per_round = c.critic_steps + c.actor_steps
    base = {
        "learner": "counterfactual",
        "in_dim": in_dim,
        "critic_in_dim": critic_in,
        "critic_obs": "privileged" if critic_true_state else typed.agent.obs,
        "actor_hidden": list(typed.agent.actor_hidden),
        "decisions": c.decisions,
        "interval": c.interval(step_s),
        "hold_s": [float(h) for h in c.hold_s],
        "step_s": float(step_s),
        "obs_dim": in_dim - 1,
        "obs": typed.agent.obs,
        "use_speed": typed.agent.use_speed,
        "frame_view": typed.agent.frame_view,
        "action_map": ActionMap().to_dict(),
        "reward": agent_id.reward,
    }

    def save(log_step: int) -> None:
        run_.save(
            {
                **base,
                "actor": actor.state_dict(),
                "critic": None if critic is None else critic.state_dict(),
                "done": list(done),
                "history": history,
                "step": log_step,
                "log_step": log_step,
            }
        )

    data_rounds: list[dict] = []
    rounds = c.dagger_rounds + 1
    first = sum(f"actor{r}" in done for r in range(rounds))
    for r in range(first, rounds):
        for past in range(len(data_rounds), r + 1):  # every round's labels so far; this round's driven by the actor
            driver = {**base, "actor": actor.state_dict()} if past == r and past > 0 else None
            n = c.episodes if past == 0 else c.dagger_episodes
            data = labels(cfg, past, n, labels_dir(cfg, past, run_.dir), driver, run_.stop)
            if data is None:
                return {"stopped": True}
            data["x"] = (
                privileged_states(data, c.decisions) if privileged else encode_states(encoder, data, c.decisions)
            )
            data["xc"] = privileged_states(data, c.decisions) if critic_true_state else data["x"]
            data["held"] = held_out_rows(data["episode"])
            data_rounds.append(data)
        x, xc, u, costs, state, held = (
            np.concatenate([d[k] for d in data_rounds]) for k in ("x", "xc", "u", "costs", "state", "held")
        )
        if f"critic{r}" not in done:
            fitted, figures = fit_critic(xc, u, costs, state, held, c, typed.seed, r, run_, r * per_round)
            if fitted is None:
                return {"stopped": True}
            critic = fitted
            history[f"critic{r}"] = {k: round(v, 6) for k, v in figures.items()}
            done.append(f"critic{r}")
            save(r * per_round + c.critic_steps - 1)
            log.info("[counterfactual] round %d critic, held out: %s", r, history[f"critic{r}"])
        figures = fit_actor(actor, critic, x, xc, state, held, c, typed.seed, r, run_, r * per_round + c.critic_steps)
        if figures is None:
            return {"stopped": True}
        history[f"actor{r}"] = {k: round(v, 6) for k, v in figures.items()}
        if r > 0:
            history[f"actor{r}"]["driver"] = driver_figures(data_rounds[r])
        done.append(f"actor{r}")
        save((r + 1) * per_round - 1)
        log.info("[counterfactual] round %d actor, held out: %s", r, history[f"actor{r}"])
    if not data_rounds:  # a finished run resumed: nothing to do, its metrics stand
        if run_.marker.exists():
            return json.loads(run_.marker.read_text())
        return {"reward": agent_id.reward, "learner": "counterfactual", "history": history}
    return {
        "reward": agent_id.reward,
        "learner": "counterfactual",
        "labelled_episodes": {f"round{r}": int(len(np.unique(d["episode"]))) for r, d in enumerate(data_rounds)},
        "labelled_states": int(sum(len(d["t"]) for d in data_rounds)),
        "history": history,
    }


def driver_figures(data: dict) -> dict:
    """On a DAgger round's labels (the previous actor driving): the labelled cost of the shifts it chose (the first
    proposal at every decision) and of braking at the same states, and how often it chose something else."""
    is_brake = ~data["u"].any(axis=2)
    has_brake = is_brake.any(1)
    brake = np.where(is_brake, data["costs"], np.inf).min(1)
    return {
        "label_cost_chosen": round(float(data["costs"][has_brake, 0].mean()), 6),
        "label_cost_braking": round(float(brake[has_brake].mean()), 6),
        "chose_other_than_braking": round(float(data["chosen"].any(axis=1).mean()), 6),
    }


# ----------------------------------------------------------------------------- acting
def build_policy(name: str, encoder, state: dict, device="cpu") -> ShiftPolicy:
    """A counterfactual actor's checkpoint as a scripted policy (``reset``, ``act``), its actor on ``device``."""
    from envs.counterfactual import ShiftSpace

    if encoder.dim + 1 != int(state["in_dim"]):
        raise StageError(
            f"the counterfactual actor {name} expects {int(state['in_dim']) - 1} world-model features, the world "
            f"model gives {encoder.dim} (vae.latent_dim / agent.use_speed changed): retrain it"
        )
    actor = actor_from_state(state).to(device)
    policy = ShiftPolicy(
        ShiftSpace(tuple(state["hold_s"]), float(state["step_s"])),
        actor_decision(actor, int(state["decisions"])),
        int(state["decisions"]),
        int(state["interval"]),
        name=name,
        encode=encoder.encode,
        note_action=encoder.note_action,
        reset_view=encoder.reset,
        bind_view=getattr(encoder, "bind", None),
    )
    policy.needs_camera = getattr(encoder, "needs_camera", True)
    return policy
