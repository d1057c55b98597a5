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
3. **Actor**: the paper's actor network (``agent.ddpg.actor_hidden``, tanh outputs u in [-1, 1]^3, its last layer at
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

import numpy as np
import torch
from tqdm import tqdm

from envs.counterfactual import ShiftPolicy
from envs.privileged import PRIVILEGED_DIM
from envs.streams import COUNTERFACTUAL_MINIBATCHES

from . import loading
from .action_map import ActionMap
from .common import (
    StageError,
    seed_everything,
    set_threads,
)
from .config import validate
from .counterfactual_labels import (
    actor_decision,
    encode_states,
    held_out_rows,
    labels,
    labels_dir,
    privileged_states,
)
from .learners.loop import Curves, HeldOutChecks, fit, fit_state, load_fit_state
from .models.counterfactual import CostCritic, ShiftActor, actor_from_state, features
from .stats import rank_agreement

log = logging.getLogger(__name__)
CHECK_EVERY = 500  # minibatches between held-out measurements in TensorBoard


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
        return critic(xt, torch.from_numpy(u.reshape(-1, u.shape[-1]))).mean(0).reshape(s, n).numpy()


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
    critic = CostCritic(x.shape[1], c.critic_members, c.critic_hidden, u_dim=u.shape[-1])
    xt, ut, yt, st = (torch.from_numpy(a[~held]) for a in (x, u, costs, state))
    critic.norm.fit(xt)
    learner = CriticFit(critic, xt, ut, yt, st, c, rng)
    callbacks = [Curves(writer, "critic/", offset=log_from)]
    if writer is not None:

        def held_out() -> dict:
            return {f"held_out_{k}": v for k, v in critic_figures(critic, x[held], u[held], costs[held]).items()}

        callbacks.append(HeldOutChecks(held_out, CHECK_EVERY, c.critic_steps, writer, "critic/", log_from))
    bar = tqdm(total=c.critic_steps, desc=f"critic (round {round_})", unit="batch", leave=False, disable=not run_)
    with bar:
        if not fit(learner, c.critic_steps, *callbacks, stop=stop, last=last, bar=bar):
            return None, None
    return critic.eval(), critic_figures(critic.eval(), x[held], u[held], costs[held])


class CriticFit:
    """The critic's fit as a ``Learner`` of the training loop (learners/loop.py): each update takes one minibatch
    of (state, proposal) pairs per member (each its own) and one optimiser step on their summed squared errors,
    plus the state heads' guess of the true state."""

    def __init__(self, critic: CostCritic, xt, ut, yt, st, c, rng):
        self.critic, self.xt, self.ut, self.yt, self.st, self.c, self.rng = critic, xt, ut, yt, st, c, rng
        self.opt = torch.optim.AdamW(critic.parameters(), lr=c.critic_lr, weight_decay=c.weight_decay)
        self.steps = 0

    def update(self) -> dict:
        c, (n_states, n_prop) = self.c, self.yt.shape
        loss = 0.0
        for m in range(c.critic_members):
            i = torch.from_numpy(self.rng.integers(0, n_states, c.batch_size))
            j = torch.from_numpy(self.rng.integers(0, n_prop, c.batch_size))
            pred, guess = self.critic.member(m, self.xt[i], self.ut[i, j], aux=True)
            loss = loss + ((pred - self.yt[i, j]) ** 2).mean() + c.aux_weight * ((guess - self.st[i]) ** 2).mean()
        self.opt.zero_grad()
        loss.backward()
        self.opt.step()
        self.steps += 1
        return {"train_mse": loss.detach() / c.critic_members}

    def state_dict(self) -> dict:
        return fit_state(self, {"critic": self.critic})

    def load_state_dict(self, state) -> None:
        load_fit_state(self, state, {"critic": self.critic})


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


def objective_of(q: torch.Tensor, u: torch.Tensor, c, scale: torch.Tensor | None = None, anchor=None):
    """``objective`` from the members' predictions ``q`` (members, ...) of the shifts ``u`` (..., 3). ``anchor``: how
    far each is from braking (a shift's squared steer and pedal by default)."""
    mean, spread = q.mean(0), q.std(0) if q.shape[0] > 1 else torch.zeros_like(q[0])
    anchor = (u[..., :2] ** 2).sum(-1) if anchor is None else anchor
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
    draws = torch.Generator().manual_seed(phase_seed(seed, round_, 3))
    learner = ActorFit(actor, critic, xt, xct, st, c, rng, draws)
    bar = tqdm(total=c.actor_steps, desc=f"actor (round {round_})", unit="batch", leave=False, disable=not run_)
    with bar:
        if not fit(learner, c.actor_steps, Curves(writer, "actor/", offset=log_from), stop=stop, last=last, bar=bar):
            return None
    figures = actor_figures(actor, critic, x[held], xc[held], c)
    for name, value in figures.items():
        if writer is not None:
            writer.add_scalar(f"actor/held_out_{name}", value, log_from + c.actor_steps - 1)
    return figures


class ActorFit:
    """The actor's fit against the frozen critic as a ``Learner`` of the training loop (learners/loop.py): each
    update takes one minibatch of training states and one optimiser step on the critic's objective of the actor's
    shifts (plus the regression towards the searched shifts, with ``c.search``)."""

    def __init__(self, actor: ShiftActor, critic: CostCritic, xt, xct, st, c, rng, draws: torch.Generator):
        self.actor, self.critic, self.xt, self.xct, self.st, self.c = actor, critic, xt, xct, st, c
        self.rng, self.draws = rng, draws
        self.opt = torch.optim.Adam(actor.parameters(), lr=c.actor_lr)
        self.steps = 0

    def update(self) -> dict:
        c, critic = self.c, self.critic
        i = torch.from_numpy(self.rng.integers(0, len(self.xt), c.batch_size))
        u, guess = self.actor(self.xt[i], aux=True)
        loss = actor_loss(critic, u, self.xct[i], c) + c.aux_weight * ((guess - self.st[i]) ** 2).mean()
        if c.search:
            target = searched_shifts(critic, u.detach(), self.xct[i], c, self.draws)
            loss = loss + c.search_weight * ((u - target) ** 2).sum(1).mean()
        self.opt.zero_grad()
        loss.backward()
        self.opt.step()
        self.steps += 1
        return {"loss": loss.detach()}

    def state_dict(self) -> dict:
        return fit_state(self, {"actor": self.actor}, self.draws)

    def load_state_dict(self, state) -> None:
        load_fit_state(self, state, {"actor": self.actor}, self.draws)


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
def run(cfg, agent_id) -> dict:
    """``agent.learner=counterfactual`` (``python -m worldmodel.train_agent``): the actor trained against the
    simulator's exact costs of its manoeuvres, in the agent's run folder."""
    from .training import TrainingRun

    if agent_id.reward != "r2":
        raise StageError("the counterfactual actor learns R2 costs (injury risk): train it with reward=r2")
    with TrainingRun.for_agent(cfg, agent_id) as run_:
        metrics = train(cfg, run_, agent_id)
        if metrics.get("stopped"):
            return run_.stopped(run_.state["step"] if run_.state else 0)
        log.info("[%s] %s; wrote %s", agent_id.policy, metrics["history"], run_.dir)
        return run_.finish(metrics)


def train(cfg, run_, agent_id) -> dict:
    """Every round's labels, critic and actor on the camera family, resuming after the last finished phase."""
    typed = validate(cfg)
    set_threads(typed.threads)
    # the training draws from its own seeded generators only; the process-wide ones are seeded too, because the
    # checkpoint saves their state, which would otherwise be whatever ran in this process before
    seed_everything(typed.seed)
    return train_rounds(typed, run_, agent_id.reward, CameraLabels(cfg, typed, run_.dir))


class CameraLabels:
    """The camera family's labelled rounds (``counterfactual_labels``) as the states the actor and the critic read:
    the world model's view, or the true state with ``obs=privileged`` (and for the critic with
    ``critic_obs=privileged``)."""

    def __init__(self, cfg, typed, run_dir):
        self.cfg, self.run_dir, self.c = cfg, run_dir, typed.agent.counterfactual
        self.privileged = typed.agent.obs == "privileged"  # the true state instead of the world model's view
        self.encoder = None if self.privileged else loading.load_world_model(cfg)
        self.in_dim = (PRIVILEGED_DIM if self.privileged else self.encoder.dim) + 1
        # the critic only trains the actor, so it may read the true state while the actor reads the world model's
        self.critic_true_state = self.privileged or self.c.critic_obs == "privileged"
        self.critic_in = PRIVILEGED_DIM + 1 if self.critic_true_state else self.in_dim
        self.settings = checkpoint_settings(
            typed, self.in_dim, self.critic_in, "privileged" if self.critic_true_state else typed.agent.obs
        )

    def round_data(self, round_: int, n: int, driver: dict | None, stop) -> dict | None:
        """Round ``round_``'s ``n`` labelled episodes (driven by the actor of ``driver`` after round 0), with their
        states ``x`` (the actor's view), ``xc`` (the critic's) and ``held`` (held out); None if stopped."""
        c = self.c
        data = labels(self.cfg, round_, n, labels_dir(self.cfg, round_, self.run_dir), driver, stop)
        if data is None:
            return None
        true_state = privileged_states(data, c.decisions)
        data["x"] = true_state if self.privileged else encode_states(self.encoder, data, c.decisions)
        data["xc"] = true_state if self.critic_true_state else data["x"]
        data["held"] = held_out_rows(data["episode"])
        return data


def train_rounds(typed, run_, reward: str, source) -> dict:
    """Every round's labels (``source.round_data``: the family's labelled states), critic and actor, resuming after
    the last finished phase; saves through ``run_``. Shared by every family's counterfactual-cost learner. A source
    with ``choices`` (K, 3), a fixed set of shifts labelled at every decision, has no actor: its policy is the
    critic's pessimistic choice among them (``choose``), as a DQN's is the best of its Q-values."""
    c = typed.agent.counterfactual
    choices = getattr(source, "choices", None)
    saved = run_.state or {}
    done = list(saved.get("done", []))
    actor, critic = networks(typed, saved, source.in_dim, source.critic_in, getattr(source, "u_dim", 3))
    if choices is not None:
        actor = None
    history = dict(saved.get("history", {}))
    if done:
        run_.resumed(f"after {done[-1]}")
    per_round = c.critic_steps + (0 if actor is None else c.actor_steps)
    base = {**source.settings, "reward": reward}

    def policy_state() -> dict:
        if actor is None:
            return {"actor": None, "critic": None if critic is None else critic.state_dict()}
        return {"actor": actor.state_dict(), "critic": None if critic is None else critic.state_dict()}

    def save(log_step: int) -> None:
        run_.save(
            {**base, **policy_state(), "done": list(done), "history": history, "step": log_step, "log_step": log_step}
        )

    data_rounds: list[dict] = []
    rounds = c.dagger_rounds + 1
    first = sum(f"actor{r}" in done for r in range(rounds))
    for r in range(first, rounds):
        for past in range(len(data_rounds), r + 1):  # every round's labels so far; this round's driven by the policy
            driver = {**base, **policy_state()} if past == r and past > 0 else None
            data = source.round_data(past, c.episodes if past == 0 else c.dagger_episodes, driver, run_.stop)
            if data is None:
                return {"stopped": True}
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
        if actor is None:
            figures = choice_figures(critic, xc[held], u[held], costs[held], choices, c)
            log_choice_figures(run_, figures, (r + 1) * per_round - 1)
        else:
            step = r * per_round + c.critic_steps
            figures = fit_actor(actor, critic, x, xc, state, held, c, typed.seed, r, run_, step)
        if figures is None:
            return {"stopped": True}
        history[f"actor{r}"] = {k: round(v, 6) for k, v in figures.items()}
        if r > 0:
            history[f"actor{r}"]["driver"] = driver_figures(data_rounds[r])
        done.append(f"actor{r}")
        save((r + 1) * per_round - 1)
        log.info(
            "[counterfactual] round %d %s, held out: %s",
            r,
            "choice" if actor is None else "actor",
            history[f"actor{r}"],
        )
    return finished_metrics(run_, reward, data_rounds, history)


# ----------------------------------------------------------------------------- choosing among fixed shifts
def choose(critic: CostCritic, x: np.ndarray, choices: np.ndarray, c) -> np.ndarray:
    """Per state of ``x`` (S, F), the index among ``choices`` (K, U: the codes the critic reads, braking's all
    zero) of the one of lowest ``objective``: the members' mean predicted cost, pessimistic by their spread and
    anchored to braking (by the code's squared length) where they disagree (the spread's scale: the state's mean
    over its choices). A fixed set's greedy policy, as a DQN's argmax is."""
    with torch.no_grad():
        xt = torch.from_numpy(np.asarray(x, np.float32))
        u = torch.from_numpy(np.asarray(choices, np.float32))[None].expand(len(xt), -1, -1)
        q = critic.grid(xt, u)
        spread = q.std(0) if q.shape[0] > 1 else torch.zeros_like(q[0])
        scale = spread.mean(1, keepdim=True).clamp_min(1e-6)
        return objective_of(q, u, c, scale, anchor=(u**2).sum(-1))[0].argmin(1).numpy()


def choice_figures(critic: CostCritic, x, u, costs, choices: np.ndarray, c) -> dict:
    """On held-out states whose labels are the ``choices`` in their order: the exact labelled cost of the critic's
    choice, of braking (the choice ``u = 0``), of the best choice, and how often it chooses other than braking."""
    if not len(x):
        return {}
    if not np.allclose(u, np.broadcast_to(choices, u.shape)):
        raise StageError("the labels hold other shifts than the learner's choices: label them again")
    pick = choose(critic, x, choices, c)
    brake = int(np.flatnonzero(~choices.any(1))[0])
    rows = np.arange(len(x))
    return {
        "exact_cost_chosen": float(costs[rows, pick].mean()),
        "exact_cost_braking": float(costs[:, brake].mean()),
        "exact_cost_best": float(costs.min(1).mean()),
        "switch_share": float((pick != brake).mean()),
    }


def log_choice_figures(run_, figures: dict, step: int) -> None:
    writer = run_.writer if run_ is not None else None
    for name, value in figures.items():
        if writer is not None:
            writer.add_scalar(f"choice/held_out_{name}", value, step)


def critic_decision(critic: CostCritic, choices: np.ndarray, decisions: int, c, shifts: np.ndarray | None = None):
    """``decide(x, d)`` of a learner that chooses among ``choices`` by its critic (``choose``): the chosen row of
    ``shifts`` (the shift parameters u of each choice; by default the choices themselves)."""
    shifts = choices if shifts is None else shifts

    def decide(x: np.ndarray, d: int) -> np.ndarray:
        inp = features(np.asarray(x, np.float32)[None], np.array([d]), decisions)
        return np.asarray(shifts[int(choose(critic, inp, choices, c)[0])], np.float32)

    return decide


def critic_from_state(state: dict) -> CostCritic:
    """The critic of a checkpoint (or a DAgger round's driver) whose settings name its shape."""
    u_dim = int(state.get("critic_u_dim", 3))
    critic = CostCritic(int(state["critic_in_dim"]), int(state["critic_members"]), state["critic_hidden"], u_dim=u_dim)
    critic.load_state_dict(state["critic"])
    return critic.eval()


def networks(typed, saved: dict, in_dim: int, critic_in: int, u_dim: int = 3) -> tuple[ShiftActor, CostCritic | None]:
    """The actor (seeded, braking at first) and the critic, with the weights of the checkpoint ``saved``."""
    c = typed.agent.counterfactual
    torch.manual_seed(phase_seed(typed.seed, 0, 2))  # the actor's initial weights (its last layer is zero)
    actor = ShiftActor(in_dim, typed.agent.ddpg.actor_hidden)
    critic = None
    if saved.get("actor") is not None:  # None: a learner choosing among fixed shifts has no actor
        actor.load_state_dict(saved["actor"])
    if saved.get("critic") is not None:
        critic = CostCritic(critic_in, c.critic_members, c.critic_hidden, u_dim=u_dim)
        critic.load_state_dict(saved["critic"])
    return actor, critic


def checkpoint_settings(typed, in_dim: int, critic_in: int, critic_obs: str) -> dict:
    """What a checkpoint records beside the weights: what the actor and the critic read, and how it drives."""
    c, step_s = typed.agent.counterfactual, typed.env.step_s
    return {
        "learner": "counterfactual",
        "in_dim": in_dim,
        "critic_in_dim": critic_in,
        "critic_obs": critic_obs,
        "actor_hidden": list(typed.agent.ddpg.actor_hidden),
        "decisions": c.decisions,
        "interval": c.interval(step_s),
        "hold_s": [float(h) for h in c.hold_s],
        "step_s": float(step_s),
        "obs_dim": in_dim - 1,
        "obs": typed.agent.obs,
        "use_speed": typed.agent.use_speed,
        "frame_view": typed.agent.frame_view,
        "action_map": ActionMap().to_dict(),
    }


def finished_metrics(run_, reward: str, data_rounds: list[dict], history: dict) -> dict:
    """The run's metrics: how many episodes and states each round labelled, and each phase's held-out figures."""
    if not data_rounds:  # a finished run resumed: nothing to do, its metrics stand
        if run_.marker.exists():
            return json.loads(run_.marker.read_text())
        return {"reward": reward, "learner": "counterfactual", "history": history}
    return {
        "reward": reward,
        "learner": "counterfactual",
        "labelled_episodes": {f"round{r}": int(len(np.unique(d["episode"]))) for r, d in enumerate(data_rounds)},
        "labelled_states": int(sum(len(d["t"]) for d in data_rounds)),
        "history": history,
    }


def driver_figures(data: dict) -> dict:
    """On a DAgger round's labels (the previous policy driving): the labelled cost of the shifts it chose (the
    proposal equal to its choice at every decision: the first for an actor, one of the fixed choices otherwise) and
    of braking at the same states, and how often it chose something else."""
    is_brake = ~data["u"].any(axis=2)
    is_chosen = (np.abs(data["u"] - data["chosen"][:, None]) < 1e-6).all(axis=2)
    has = is_brake.any(1) & is_chosen.any(1)
    brake = np.where(is_brake, data["costs"], np.inf).min(1)
    chosen = data["costs"][np.arange(len(is_chosen)), is_chosen.argmax(1)]
    return {
        "label_cost_chosen": round(float(chosen[has].mean()), 6),
        "label_cost_braking": round(float(brake[has].mean()), 6),
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
