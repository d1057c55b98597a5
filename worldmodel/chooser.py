"""The chooser agent (``agent.learner=chooser``; docs/design.md §5): the costs of manoeuvres, learnt from the camera.

``envs/chooser.py`` holds the decision rule: brake from onset, and switch once, within the first ``decide_s``
seconds, to the candidate manoeuvre whose predicted R2 cost is lowest when it beats braking by more than
``margin``. This module learns the prediction:

1. **Labels** (``labels``, worldmodel/chooser_labels.py): straight-line braking through ``chooser.episodes``
   scenarios with the camera on; at each decision step the simulator gives the exact cost of starting every
   candidate there (the planner's re-simulation, ``envs.planner.plan_cost``). Stored under
   ``data/NAME/chooser_labels/<settings>-seed<S>/`` in HDF5 shards, written atomically; an interrupted labelling
   continues where it stopped.
2. **Scorer** (``train``): every labelled frame through the frozen world model exactly as a live run feeds it
   (``encode_episode``, braking actions), plus the decision step, normalised by fixed per-feature statistics of
   the training split; an MLP regresses all candidates' costs by least squares, i.e. their expectation given what
   the camera shows. The scorer kept is the one whose chooser costs least on the held-out labelled episodes.

Because the chooser brakes until it switches, its decision states are exactly the labelled ones, and its cost on a
labelled episode is known without simulating (``policy_cost``): braking's cost up to the switch plus the exact cost
of the chosen manoeuvre from there. That is the selection criterion, and ``metrics.json`` reports it beside braking
and the exact-cost chooser (the same rule with the true costs: this agent's ceiling).
"""

from __future__ import annotations

import logging

import numpy as np
import torch
from tqdm import tqdm

from envs.chooser import BRAKE, ManoeuvreChooser, decide_steps_for, switch_choice
from envs.planner import Manoeuvre
from envs.scene import CLASS_NAMES
from envs.streams import CHOOSER_MINIBATCHES
from envs.views import MaskView

from . import artifacts, loading

# the labels, which the experiments and the tests also read through this module
from .chooser_labels import (  # noqa: F401
    LABEL_KEYS,
    SHARD,
    SOURCES,
    STATIC_KEY,
    TELE_KEY,
    cfg_chooser,
    label_scenario,
    label_seed,
    labels,
    labels_dir,
    validation_entries,
)
from .common import StageError, resolve_device, reuse_freed_memory, seed_everything, set_threads
from .config import validate
from .learners.loop import Curves, HeldOutChecks, fit, fit_state, load_fit_state
from .models.chooser import Scorer, ScorerInputs

log = logging.getLogger(__name__)
# the frame band the scorer's CNN reads, per camera (agent.chooser.mask_camera): the rows where road users from
# ~4 m to the far end of the street appear; in the 30-degree camera the hazard pedestrians of the validation bank
# fall in rows 8-46 on braking's first three frames
MASK_ROWS = {"wide": (20, 44), "tele": (8, 48)}
MASK_OBS = {"wide": "seg", "tele": TELE_KEY}
HELD_OUT = 0.15  # share of labelled episodes held out for selecting the scorer


# ----------------------------------------------------------------------------- the scorer's inputs
def features(encoded: np.ndarray, t: np.ndarray, decide_steps: int) -> np.ndarray:
    """The scorer's input: the agent input of the world model, then the decision step as a share of the window."""
    return np.concatenate([encoded, (np.asarray(t, np.float32) / decide_steps)[:, None]], axis=1).astype(np.float32)


def band_masks(seg: np.ndarray, episode: np.ndarray, rows: tuple[int, int] = MASK_ROWS["wide"]):
    """``MaskView``'s class masks of every labelled frame as uint8 ``(N, classes, band rows, W)``, and for each frame
    the row of the one before it in its episode (-1 for the first), which ``MaskView`` pairs it with."""
    view = MaskView(rows)
    ids = np.array([CLASS_NAMES.index(c) for c in view.classes], np.uint8)
    band = np.asarray(seg)[:, view.rows[0] : view.rows[1]]
    current = np.equal(band[:, None], ids[:, None, None]).view(np.uint8)  # 0/1, as MaskView's floats
    order = np.lexsort((np.arange(len(episode)), episode))  # each episode's rows in order
    previous = np.full(len(episode), -1, np.int64)
    same = episode[order][1:] == episode[order][:-1]
    previous[order[1:][same]] = order[:-1][same]
    return current, previous


def scorer_inputs(encoder, data: dict, steps: int, mask_view: bool, camera: str = "wide") -> ScorerInputs:
    """Everything the scorer reads for every labelled frame: world-model features, decision step, and the frame
    band of ``camera``."""
    x = features(encode_labels(encoder, data), data["t"], steps)
    if not mask_view:
        return ScorerInputs(x)
    if MASK_OBS[camera] not in data:
        raise StageError(
            f"the chooser's frame band reads the {camera} camera, and these labels have no {MASK_OBS[camera]!r} "
            "frames: set env.tele_fov_deg (e.g. 30) to give the env its second camera"
        )
    return ScorerInputs(x, *band_masks(data[MASK_OBS[camera]], data["episode"], MASK_ROWS[camera]))


def policy_choices(pred: np.ndarray, episode: np.ndarray, margin: float, t=None, steps=None, min_brake_cost=0.0):
    """Per labelled episode, where the chooser that acts on ``pred`` switches: braking until the first step where
    some candidate is predicted cheaper than braking by more than ``margin`` (and, when ``min_brake_cost`` is set,
    braking is predicted to cost more than it), then that candidate. With ``t`` and ``steps``: a chooser whose
    window ends after ``steps`` decision steps. Returns row indices ``first`` (the episode's first decision),
    ``at`` (the switch, -1 for none) and the candidate ``k`` (0, braking, for none)."""
    first, at, ks = [], [], []
    for e in np.unique(episode):
        rows = np.flatnonzero(episode == e)
        if t is not None and steps is not None:
            rows = rows[np.asarray(t)[rows] < steps]
        first.append(rows[0])
        at.append(-1)
        ks.append(0)
        for row in rows:
            k = switch_choice(pred[row], margin, min_brake_cost)
            if k is not None:
                at[-1], ks[-1] = row, k
                break
    return np.asarray(first), np.asarray(at), np.asarray(ks)


def policy_cost(pred: np.ndarray, costs: np.ndarray, episode: np.ndarray, margin: float, **window) -> np.ndarray:
    """Per labelled episode, the exact R2 cost of the chooser that acts on ``pred`` (``policy_choices``; ``window``:
    its ``t``, ``steps``, ``min_brake_cost``): braking's cost up to the switch plus the chosen candidate's after."""
    first, at, k = policy_choices(pred, episode, margin, **window)
    out = costs[first, 0].astype(np.float64)
    s = at >= 0
    out[s] += costs[at[s], k[s]] - costs[at[s], 0]
    return out


def policy_static(pred: np.ndarray, static: np.ndarray, episode: np.ndarray, margin: float, **window) -> np.ndarray:
    """Per labelled episode, whether the chooser that acts on ``pred`` hits a static object (labels' ``static``)."""
    first, at, k = policy_choices(pred, episode, margin, **window)
    return np.where(at >= 0, static[np.maximum(at, 0), k], static[first, 0]).astype(bool)


def encode_labels(encoder, data: dict) -> np.ndarray:
    """Every labelled frame as a live chooser's encoder sees it (braking before every frame)."""
    from .agent_obs import encode_episode

    out = np.empty((len(data["speed"]), encoder.dim), np.float32)
    for e in tqdm(np.unique(data["episode"]), desc="encode chooser labels", unit="episode"):
        rows = np.flatnonzero(data["episode"] == e)
        brake = np.repeat(BRAKE[None], len(rows), axis=0)
        out[rows] = encode_episode(encoder, data["seg"][rows], data["speed"][rows], brake)
    return out


def held_out_split(episode: np.ndarray) -> np.ndarray:
    """True for the rows of the last ``HELD_OUT`` share of labelled episodes."""
    episodes = np.unique(episode)
    held = episodes[int(round(len(episodes) * (1 - HELD_OUT))) :]
    return np.isin(episode, held)


STATE_SCALE = np.array([1.0, 10.0, 5.0, 5.0, 5.0, 1.0, 10.0, 5.0, 5.0, 5.0], np.float32)  # ~unit targets


def fit_scorer(
    x: ScorerInputs | np.ndarray,
    y: np.ndarray,
    episode: np.ndarray,
    c,
    seed: int,
    writer=None,
    stop=None,
    state=None,
    device="cpu",
):
    """Fit a ``Scorer`` on the training split (its ``target`` loss, plus ``c.aux_weight`` times the squared error
    of its guess of the privileged hazard ``state``, which shapes what its first layer perceives); keep the
    checkpoint whose chooser costs least on the held-out split. Returns (scorer, history of (minibatch,
    held-out cost, held-out mse)). The scorer and the training split live on ``device``; the minibatches are
    drawn on the CPU, the same on every device (dropout's masks are the device's own). The rows of a minibatch
    are put together when it is drawn (``ScorerInputs``), so the frame band is never held as floats whole."""
    device = torch.device(device)
    reuse_freed_memory()
    torch.manual_seed(int(seed))
    x = x if isinstance(x, ScorerInputs) else ScorerInputs(np.asarray(x, np.float32))
    is_held = held_out_split(episode)
    aux_weight = c.aux_weight
    if aux_weight > 0 and state is None:
        raise StageError("chooser.aux_weight > 0 needs labels with the hazard state: relabel them")
    st = torch.from_numpy(state[~is_held] / STATE_SCALE).to(device) if aux_weight > 0 else None
    xt, yt = x.subset(~is_held), torch.from_numpy(y[~is_held]).to(device)
    xv, yv, ev = x.subset(is_held), y[is_held], episode[is_held]
    members = c.ensemble
    mask_shape = MaskView(MASK_ROWS[c.mask_camera]).shape if c.mask_view else None
    scorer = Scorer(x.shape[1], y.shape[1], tuple(c.hidden), c.dropout, members, c.target, mask_shape)
    vec = torch.from_numpy(xt.vec[xt.index, : x.shape[1] - scorer.mask_dim])  # the features the scorer normalises
    scorer.mean.copy_(vec.mean(0))
    scorer.std.copy_(vec.std(0).clamp_min(1e-2))  # a feature constant in training (an empty profile row) stays 0
    scorer.to(device)  # built on the CPU from the seed: the same initial weights on every device
    opt = torch.optim.AdamW(scorer.parameters(), lr=c.lr, weight_decay=c.weight_decay)
    rng = np.random.default_rng([int(seed), CHOOSER_MINIBATCHES])
    learner = ScorerFit(scorer, opt, xt, yt, st, aux_weight, c.batch_size, rng, device)

    def held_out() -> dict:
        scorer.eval()
        pred = scorer.predict(xv)
        scorer.train()
        return {
            "held_out_cost": float(policy_cost(pred, yv, ev, c.margin).mean()),
            "held_out_mse": float(((pred - yv) ** 2).mean()),
        }

    checks = HeldOutChecks(held_out, 250, c.steps, writer, "chooser/", keep=scorer, best_of="held_out_cost")
    bar = tqdm(total=c.steps, desc="chooser scorer", unit="batch", disable=writer is None)
    with bar:
        fit(learner, c.steps, Curves(writer, "chooser/"), checks, stop=stop, bar=bar)
    checks.restore()
    history = [(k, f["held_out_cost"], f["held_out_mse"]) for k, f in checks.history]
    return scorer.eval(), history


class ScorerFit:
    """The scorer's fit as a ``Learner`` of the training loop (learners/loop.py): each update takes one minibatch
    of the training split per ensemble member (each member its own) and one optimiser step on their summed
    loss."""

    def __init__(self, scorer: Scorer, opt, xt: ScorerInputs, yt, st, aux_weight: float, batch_size: int, rng, device):
        self.scorer, self.opt, self.xt, self.yt, self.st = scorer, opt, xt, yt, st
        self.aux_weight, self.batch_size, self.rng, self.device = aux_weight, batch_size, rng, device
        self.members = len(scorer.nets)
        self.steps = 0

    def update(self) -> dict:
        scorer, loss = self.scorer, 0.0
        for m in range(self.members):
            drawn = self.rng.integers(0, len(self.xt), size=self.batch_size)
            idx, rows = torch.from_numpy(drawn).to(self.device), torch.from_numpy(self.xt[drawn]).to(self.device)
            if self.aux_weight > 0:
                out, guess = scorer.raw(rows, m, aux=True)
                loss = loss + scorer.loss(out, self.yt[idx]) + self.aux_weight * ((guess - self.st[idx]) ** 2).mean()
            else:
                loss = loss + scorer.loss(scorer.raw(rows, m), self.yt[idx])
        self.opt.zero_grad()
        loss.backward()
        self.opt.step()
        self.steps += 1
        return {"train_loss": loss.detach() / self.members}  # a tensor: read only where a curve is written

    def state_dict(self) -> dict:
        return {**fit_state(self, {"scorer": self.scorer}), "torch_rng": torch.get_rng_state()}  # dropout's, on the CPU

    def load_state_dict(self, state) -> None:
        load_fit_state(self, state, {"scorer": self.scorer})
        torch.set_rng_state(state["torch_rng"])


# settings of the decision rule alone: the scorer is fitted and kept as without them, so a finished run resumed
# (resume=true) with only these changed keeps its scorer and applies them, in seconds rather than a refit
DECISION_KEYS = ("min_brake_cost",)


def fit_identity(cfg) -> str:
    """The hash of everything that shapes the fitted scorer: the agent's provenance without ``DECISION_KEYS``."""
    from omegaconf import OmegaConf

    fitted = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    for key in (*DECISION_KEYS, "num_workers"):  # labels are the same for any worker count (tests/test_chooser.py)
        fitted.agent.chooser[key] = None
    return artifacts.config_sha256(artifacts.provenance(fitted, "agent"))


def checkpoint_settings(typed, reward: str, candidates, steps: int, in_dim: int, obs_dim: int) -> dict:
    """What a chooser's checkpoint records beside the scorer: its inputs, its candidates and its decision rule."""
    from .action_map import ActionMap

    c = typed.agent.chooser
    return {
        "learner": "chooser",
        "in_dim": in_dim,
        "hidden": list(c.hidden),
        "dropout": c.dropout,
        "members": c.ensemble,
        "target": c.target,
        "mask_view": c.mask_view,
        "mask_camera": c.mask_camera,
        "tele_fov_deg": typed.env.tele_fov_deg if c.mask_view and c.mask_camera == "tele" else None,
        "candidates": [vars(m) for m in candidates],
        "decide_steps": steps,
        "margin": c.margin,
        "min_brake_cost": c.min_brake_cost,
        "obs_dim": obs_dim,
        "use_speed": typed.agent.use_speed,
        "frame_view": typed.agent.frame_view,
        "action_map": ActionMap().to_dict(),
        "reward": reward,
        "step": c.steps,
    }


def run(cfg, agent_id) -> dict:
    """``agent.learner=chooser`` (``python -m worldmodel.train_agent``): label, encode and fit the scorer in the
    agent's run folder."""
    from .training import TrainingRun

    if agent_id.reward != "r2":
        raise StageError("the chooser learns R2 costs (injury risk): train it with reward=r2")
    with TrainingRun.for_agent(cfg, agent_id) as run_:
        if run_.state is not None:  # the scorer trains in minutes: a stopped run starts again (labels are kept)
            run_.resumed("refitting the scorer from the stored labels, unless only its decision rule changed")
        metrics = train(cfg, run_, agent_id)
        if run_.stop.requested:
            return run_.stopped(0)
        log.info("[%s] held-out R2 cost per episode: %s; wrote %s", agent_id.policy, metrics["held_out_cost"], run_.dir)
        return run_.finish(metrics)


def train(cfg, run_, agent_id) -> dict:
    """Label (or reuse labels), encode, fit the scorer; saves the chooser's checkpoint through ``run_``."""
    typed = validate(cfg)
    c = typed.agent.chooser
    set_threads(typed.threads)
    seed_everything(typed.seed)
    steps = decide_steps_for(c.decide_s, typed.env.step_s)
    candidates = c.candidates(typed.env.step_s)
    data = labels(cfg)
    encoder = loading.load_world_model(cfg)
    x = scorer_inputs(encoder, data, steps, c.mask_view, c.mask_camera)
    for frames in ("seg", TELE_KEY):  # read into the inputs: ~0.5 GB with 15,000 labelled episodes
        data.pop(frames, None)
    y = data["costs"].astype(np.float32)
    static = data.get(STATIC_KEY)
    if c.static_penalty > 0 and static is None:
        raise StageError(
            f"agent.chooser.static_penalty={c.static_penalty} needs labels that record static collisions, and "
            f"{labels_dir(cfg)} predates them: delete that folder and rerun to relabel"
        )
    # what the scorer learns and its checkpoint is chosen on: the costs, plus the penalty where a pole is hit
    y_fit = y + np.float32(c.static_penalty) * static if c.static_penalty > 0 else y
    fitted = fit_identity(cfg)
    finished = run_.state is not None and run_.marker.exists()  # a stopped fit saved a partial scorer: refit it
    if finished and run_.state.get("fit_identity") == fitted:
        log.info(
            "[chooser] the scorer in %s was fitted on these inputs and settings: kept, the decision rule's "
            "settings (%s) applied to it",
            run_.last,
            ", ".join(DECISION_KEYS),
        )
        scorer = scorer_from_state(run_.state)
        history = [(k["step"], k["held_out_cost"], k["held_out_mse"]) for k in run_.state["checks"]]
    else:
        device = resolve_device(typed.device)
        scorer, history = fit_scorer(
            x, y_fit, data["episode"], c, typed.seed, run_.writer, run_.stop, data["state"], device
        )
    is_held = held_out_split(data["episode"])
    yv, ev = y[is_held], data["episode"][is_held]
    pred = scorer.predict(x.subset(is_held))
    exact = policy_cost(yv, yv, ev, 0.0)
    braking = yv[np.r_[True, ev[1:] != ev[:-1]], 0]
    margins = {m: float(policy_cost(pred, yv, ev, m).mean()) for m in (0.0, 0.01, 0.02, 0.05, 0.1)}
    rule = {"min_brake_cost": c.min_brake_cost}
    checks = [{"step": s, "held_out_cost": round(v, 5), "held_out_mse": round(m, 6)} for s, v, m in history]
    settings = checkpoint_settings(typed, agent_id.reward, candidates, steps, int(x.shape[1]), int(encoder.dim))
    head = {"learner": "chooser", "fit_identity": fitted, "checks": checks, "scorer": scorer.state_dict()}
    # a stopped fit is refitted from its first minibatch on resume: its curves are then purged from there
    run_.save({**head, **settings, "log_step": -1 if run_.stop.requested else c.steps})
    return {
        "reward": agent_id.reward,
        "learner": "chooser",
        "labelled_episodes": int(len(np.unique(data["episode"]))),
        "labelled_states": int(len(y)),
        "held_out_episodes": int(len(np.unique(ev))),
        "held_out_cost": {
            "braking": round(float(braking.mean()), 5),
            "exact_chooser": round(float(exact.mean()), 5),
            "learned": round(float(policy_cost(pred, yv, ev, c.margin, **rule).mean()), 5),
            "learned_by_margin": {str(m): round(v, 5) for m, v in margins.items()},
        },
        # the share of held-out episodes that end in a static object (labels without the flags: absent)
        **(
            {}
            if static is None
            else {
                "held_out_static": {
                    "exact_chooser": round(float(policy_static(yv, static[is_held], ev, 0.0).mean()), 5),
                    "learned": round(float(policy_static(pred, static[is_held], ev, c.margin, **rule).mean()), 5),
                }
            }
        ),
        "checks": checks,
    }


# ----------------------------------------------------------------------------- acting
class LearnedScorer:
    """The trained scorer behind ``ManoeuvreChooser``'s ``scores(obs, t)``, with the world model's state."""

    def __init__(self, encoder, scorer: Scorer, decide_steps: int, camera: str = "wide"):
        self.encoder, self.scorer, self.decide_steps = encoder, scorer.eval(), int(decide_steps)
        self.mask = MaskView(MASK_ROWS[camera]) if scorer.mask_shape else None
        self.mask_obs = MASK_OBS[camera]

    def reset(self) -> None:
        self.encoder.reset()
        if self.mask is not None:
            self.mask.reset()

    def note_action(self, action) -> None:
        self.encoder.note_action(action)

    def __call__(self, obs, t: int) -> np.ndarray:
        x = features(self.encoder.encode(obs)[None], np.array([t]), self.decide_steps)
        if self.mask is not None:
            if self.mask_obs not in obs:
                raise StageError(
                    f"this chooser reads the frames of a second camera ({self.mask_obs!r}) that the env does not "
                    "render: set env.tele_fov_deg to the field of view it was trained with"
                )
            x = np.concatenate([x, self.mask(obs[self.mask_obs])[None]], axis=1)
        with torch.inference_mode():
            return self.scorer(torch.from_numpy(x).to(self.scorer.mean.device))[0].cpu().numpy()


def scorer_from_state(state: dict) -> Scorer:
    """The fitted scorer of a chooser checkpoint, in eval mode."""
    camera = str(state.get("mask_camera", "wide"))  # absent: a chooser trained before the second camera
    scorer = Scorer(
        int(state["in_dim"]),
        len(state["candidates"]),
        tuple(state["hidden"]),
        float(state["dropout"]),
        int(state.get("members", 1)),
        str(state.get("target", "cost")),
        MaskView(MASK_ROWS[camera]).shape if state.get("mask_view") else None,
    )
    scorer.load_state_dict(state["scorer"])
    return scorer.eval()


def build_policy(name: str, encoder, state: dict, margin: float | None = None, device="cpu") -> ManoeuvreChooser:
    """A chooser checkpoint as a scripted-policy (``reset``, ``act``), its scorer on ``device``."""
    candidates = [Manoeuvre(**m) for m in state["candidates"]]
    camera = str(state.get("mask_camera", "wide"))
    scorer = scorer_from_state(state).to(device)
    if encoder.dim + 1 + scorer.mask_dim != int(state["in_dim"]):
        raise StageError(
            f"the chooser {name} expects {int(state['in_dim']) - 1} world-model features, the world model gives "
            f"{encoder.dim} (vae.latent_dim / agent.use_speed / agent.frame_view changed): retrain it"
        )
    learned = LearnedScorer(encoder, scorer, int(state["decide_steps"]), camera)
    return ManoeuvreChooser(
        candidates,
        learned,
        int(state["decide_steps"]),
        float(state["margin"] if margin is None else margin),
        name=name,
        min_brake_cost=float(state.get("min_brake_cost", 0.0)),  # absent: a chooser trained before the option
        reset_scorer=learned.reset,
        note_action=learned.note_action,
        env_overrides={"tele_fov_deg": float(state["tele_fov_deg"])} if state.get("tele_fov_deg") else None,
    )
