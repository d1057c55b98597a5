"""The LIDAR chooser on family kim (``agent=kim_chooser``): learn what each manoeuvre would cost, not what the
planner did.

    python -m worldmodel.train_agent experiment=NAME agent=kim_chooser [seed=K]

The cloned LIDAR students stop at straight-line braking because the planner's choices, rare swerves that flicker
from step to step, are what they cannot copy (docs/results/kim/README.md). The chooser (``envs/chooser.py``,
docs/design.md §5) learns the exact cost of every candidate manoeuvre instead and, because it brakes until it
switches once, decides only in braking's own states, which the labels hold exactly.

**Labels** (``labels``): straight-line braking through ``agent.kim_chooser.episodes`` training-distribution
episodes (stream ``KIM_CHOOSER_LABELS`` of ``label_seed``, apart from the DDPG's and the students'); at each of the
first ``decide_s`` seconds the LIDAR view the agent would see and, by re-simulation, the exact cost (Kim's
``kim_unaware``: the summed ISS of the crashes to come, 0 when nothing is hit) of starting each candidate there.
They do not depend on the training seed, so they are made once per experiment and label settings and kept in
``data/NAME/kim_chooser_labels/``, for every seed.

**Scorer** (``fit``): an MLP regresses all candidates' costs from the view and the decision step, by least squares,
on the first 85 % of the labelled episodes; the epoch kept is the one whose chooser avoids most on the last 15 %.
Because the decisions happen in labelled states, a rule's outcome is known without simulating (``outcomes``):
braking's cost if it never switches, else the chosen candidate's exact cost where it switched.
"""

from __future__ import annotations

import logging

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from envs.chooser import BRAKE, ManoeuvreChooser, decide_steps_for, switch_choice
from envs.kim import kim_action_for
from envs.planner import Manoeuvre, _Plan, plan_cost
from envs.streams import KIM_CHOOSER_LABELS

from ... import artifacts
from ...common import StageError, atomic_output
from ...learners import loop
from .observe import LidarObserver, family_env, observer, training_scenario

log = logging.getLogger(__name__)
LEARNER = "kim_chooser"
REWARD = "kim_unaware"  # the cost whose zero is an avoided runner: the chooser learns it and nothing else
HELD_OUT = 0.15  # the share of labelled episodes, the last ones, on which the epoch is chosen
LR = 1e-3  # Adam's
BATCH = 128  # labelled states per minibatch, about


def candidates(step_s: float = 0.1) -> list[Manoeuvre]:
    """Braking first (the chooser's default), then holding the speed or accelerating straight on (a runner that
    strikes behind the ego's front is dodged by getting there first), then every steer x shape x pedal x side."""
    out = [Manoeuvre(-1.0), Manoeuvre(0.0), Manoeuvre(1.0)]
    shapes = [("swerve", 0)] + [("lane_change", max(1, round(h / step_s))) for h in (0.3, 0.6)]
    for steer in (0.3, 1.0):
        for shape, hold in shapes:
            for pedal in (-1.0, 0.0, 1.0):
                for side in (1.0, -1.0):
                    out.append(Manoeuvre(pedal, side * steer, 0, shape, hold))
    return out


def label_episodes(cfg, specs: list, decide_steps: int, stop=None) -> dict | None:
    """Braking through each scenario of ``specs``: per decision step, the LIDAR view (``view``), every candidate's
    exact cost from there (``cost``), the scenario's index (``episode``), the step (``step``) and the ego's speed
    (``speed``, m/s: what a candidate's pedal asks of Kim's speed controller). None if ``stop`` was requested
    first."""
    env = family_env(cfg, REWARD)
    twin = env.planning_twin()
    see = observer(cfg, REWARD)
    moves = candidates(env.step_s)
    view, cost, episode, step, speed = [], [], [], [], []
    for e, spec in enumerate(tqdm(specs, desc="braking, every candidate costed", unit="episode")):
        if stop is not None and stop.requested:
            env.close()
            return None
        env.reset(options={"scenario": spec})
        see.reset(None)
        for t in range(decide_steps):
            snap = env.snapshot()
            view.append(see(env))
            cost.append([plan_cost(twin, snap, _Plan(m, t), reward=REWARD) for m in moves])
            episode.append(e)
            step.append(t)
            speed.append(env.ego.v)
            see.note_action(kim_action_for(BRAKE, env.ego.v))
            _, _, terminated, truncated, _ = env.step(BRAKE)
            if terminated or truncated:
                break
    env.close()
    return {
        "view": np.asarray(view, np.float32),
        "cost": np.asarray(cost, np.float32),
        "episode": np.asarray(episode),
        "step": np.asarray(step),
        "speed": np.asarray(speed, np.float32),
    }


def labels_path(cfg, typed):
    """``data/NAME/kim_chooser_labels/<hash>-seed<label seed>.npz``: the hash of everything the labels depend on
    (the episodes, the window, the candidates, the LIDAR view, the training distribution and the env), not of
    the training seed, so the seeds of an experiment share one file. ``typed``: ``validate(cfg)``."""
    from ...config import section

    a, c = typed.agent, typed.agent.kim_chooser
    settings = {
        "episodes": c.episodes,
        "decide_steps": decide_steps_for(c.decide_s, typed.env.step_s),
        "candidates": [vars(m) for m in candidates(typed.env.step_s)],
        "lidar": [a.lidar_scans, a.lidar_rays, a.use_speed],
        "impact_offset_spread": a.kim.impact_offset_spread,
        "env": section(cfg, "env"),
    }
    name = f"{artifacts.config_sha256(settings)[:10]}-seed{c.label_seed}.npz"
    return artifacts.data_dir(cfg) / "kim_chooser_labels" / name


def labels(cfg, stop=None) -> dict | None:
    """The training labels of ``cfg``'s agent section, made and stored if missing (None if ``stop`` was requested
    while labelling)."""
    from ...config import validate

    typed = validate(cfg)
    c = typed.agent.kim_chooser
    path = labels_path(cfg, typed)
    if path.exists():
        log.info("[kim chooser] labels of %d episodes from %s", c.episodes, path)
        return dict(np.load(path))
    specs = [training_scenario(typed, KIM_CHOOSER_LABELS, e, seed=c.label_seed) for e in range(c.episodes)]
    data = label_episodes(cfg, specs, decide_steps_for(c.decide_s, typed.env.step_s), stop)
    if data is None:
        return None
    with atomic_output(path) as tmp, open(tmp, "wb") as fh:  # a file object: np.savez would add .npz to a name
        np.savez(fh, **data)
    log.info("[kim chooser] wrote %s: %d decision states of %d episodes", path, len(data["view"]), c.episodes)
    return data


def window(data: dict, decide_steps: int) -> dict:
    """Labels of a longer decision window cut to the first ``decide_steps`` steps; a shorter one is refused."""
    longest = int(data["step"].max()) + 1
    if longest < decide_steps:
        raise StageError(f"these labels hold {longest} decision steps, the chooser asks for {decide_steps}: relabel")
    keep = data["step"] < decide_steps
    return {k: v[keep] for k, v in data.items()}


def features(data: dict, decide_steps: int) -> np.ndarray:
    return np.concatenate([data["view"], np.eye(decide_steps, dtype=np.float32)[data["step"]]], 1)


def outcomes(cost: np.ndarray, scores: np.ndarray, episode: np.ndarray, margin: float) -> np.ndarray:
    """Per episode, the cost of the brake-then-switch-once rule acting on ``scores``: exact, because it decides
    only in braking's states, whose candidates' costs are labelled."""
    out = []
    for e in np.unique(episode):
        rows = np.flatnonzero(episode == e)
        result = cost[rows[0], 0]  # braking throughout
        for r in rows:
            k = switch_choice(scores[r], margin)
            if k is not None:
                result = cost[r, k]
                break
        out.append(result)
    return np.asarray(out)


def held_out(episode: np.ndarray) -> np.ndarray:
    """True for the rows of the last ``HELD_OUT`` share of labelled episodes."""
    return episode >= np.quantile(np.unique(episode), 1.0 - HELD_OUT)


class Scorer(nn.Module):
    def __init__(self, inputs: int, outputs: int, hidden: int = 256):
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(inputs, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, outputs)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


def fit(train: dict, decide_steps: int, seed: int, margin: float, epochs: int = 60, hidden: int = 256, writer=None):
    """The scorer of the epoch whose chooser avoids most on the held-out episodes, and (kept epoch, its held-out
    avoided share)."""
    torch.manual_seed(seed)
    x, y, ep = features(train, decide_steps), train["cost"], train["episode"]
    held = held_out(ep)
    scorer = Scorer(x.shape[1], y.shape[1], hidden)
    learner = EpochFit(scorer, torch.from_numpy(x[~held]), torch.from_numpy(y[~held]), np.random.default_rng(seed))

    def avoided() -> dict:
        with torch.no_grad():
            pred = scorer(torch.from_numpy(x[held])).numpy()
        return {"held_out_avoided": float(np.mean(outcomes(y[held], pred, ep[held], margin) == 0))}

    # curves at the epoch's count: a step of this fit is an epoch
    checks = loop.HeldOutChecks(
        avoided, 1, epochs, writer, "kim_chooser/", 1, keep=scorer, best_of="held_out_avoided", higher_is_better=True
    )
    loop.fit(learner, epochs, loop.Curves(writer, "kim_chooser/", every=1, offset=1), checks)
    checks.restore()
    return scorer.eval(), checks.best_step, checks.best_figure


class EpochFit:
    """The scorer's fit as a ``Learner`` of the training loop (worldmodel/learners/loop.py), one epoch an update:
    the training rows in a fresh random order, in minibatches of about ``BATCH``, one Adam step each."""

    def __init__(self, scorer: Scorer, xs: torch.Tensor, ys: torch.Tensor, rng):
        self.scorer, self.xs, self.ys, self.rng = scorer, xs, ys, rng
        self.opt = torch.optim.Adam(scorer.parameters(), lr=LR)
        self.steps = 0

    def update(self) -> dict:
        xs, ys = self.xs, self.ys
        for idx in np.array_split(self.rng.permutation(len(xs)), max(1, len(xs) // BATCH)):
            loss = ((self.scorer(xs[idx]) - ys[idx]) ** 2).mean()
            self.opt.zero_grad()
            loss.backward()
            self.opt.step()
        self.steps += 1
        return {"train_loss": loss.detach()}  # the epoch's last minibatch

    def state_dict(self) -> dict:
        return loop.fit_state(self, {"scorer": self.scorer})

    def load_state_dict(self, state) -> None:
        loop.load_fit_state(self, state, {"scorer": self.scorer})


def held_out_report(data: dict, scorer: Scorer, decide_steps: int, margin: float) -> dict:
    """Avoided share and mean injury (minus the ISS) on the held-out episodes: braking, the learned chooser and the
    exact-cost chooser (the same rule on the true costs: the ceiling of these candidates)."""
    held = held_out(data["episode"])
    c, ep = data["cost"][held].astype(np.float64), data["episode"][held]
    with torch.no_grad():
        predicted = scorer(torch.from_numpy(features(data, decide_steps)[held])).numpy()
    out = {"episodes": len(np.unique(ep))}
    for who, scores, m in (("braking", np.zeros_like(c), 0.0), ("learned", predicted, margin), ("exact", c, 0.0)):
        res = outcomes(c, scores, ep, m)
        out[who] = {"avoided": round(float(np.mean(res == 0)), 4), "injury": round(float(-res.mean()), 3)}
    return out


def train(cfg, run_, agent_id) -> dict:
    """``train_agent`` with ``agent.learner=kim_chooser``: label (or reuse the experiment's labels) and fit."""
    from ...config import validate

    if agent_id.reward != REWARD:
        raise StageError(f"the LIDAR chooser learns Kim's {REWARD} costs: train it with reward={REWARD}")
    typed = validate(cfg)
    c = typed.agent.kim_chooser
    state = run_.state
    if state is not None and run_.marker.exists() and state["provenance"]["config"] == run_.record["config"]:
        run_.resumed("finished with these settings: the fitted scorer is kept")
        return state["metrics"]
    data = labels(cfg, run_.stop)
    if data is None:
        return run_.stopped(0)
    steps = decide_steps_for(c.decide_s, typed.env.step_s)
    scorer, epoch, avoided = fit(data, steps, typed.seed, c.margin, c.epochs, c.hidden, run_.writer)
    metrics = {
        "reward": agent_id.reward,
        "learner": LEARNER,
        "labelled_episodes": len(np.unique(data["episode"])),
        "labelled_states": len(data["view"]),
        "kept_epoch": epoch,
        "held_out": held_out_report(data, scorer, steps, c.margin),
    }
    run_.save(
        {
            "learner": LEARNER,
            "obs": "lidar",
            "scorer": scorer.state_dict(),
            "inputs": int(data["view"].shape[1]) + steps,
            "hidden": c.hidden,
            "candidates": [vars(m) for m in candidates(typed.env.step_s)],
            "decide_steps": steps,
            "margin": c.margin,
            "lidar_scans": typed.agent.lidar_scans,
            "lidar_rays": typed.agent.lidar_rays,
            "lidar_speed": typed.agent.use_speed,
            "reward": agent_id.reward,
            "step": c.epochs,
            "metrics": metrics,
        }
    )
    return metrics


def summary(metrics: dict) -> str:
    h = metrics["held_out"]
    return (
        f"{metrics['labelled_episodes']} labelled episodes, epoch {metrics['kept_epoch']} kept; on the "
        f"{h['episodes']} held out it avoids {100 * h['learned']['avoided']:.1f} % (braking "
        f"{100 * h['braking']['avoided']:.1f} %, exact costs {100 * h['exact']['avoided']:.1f} %)"
    )


# ----------------------------------------------------------------------------- acting
class LidarScores:
    """The fitted scorer behind ``ManoeuvreChooser``: the LIDAR view at each decision step, as labelled."""

    def __init__(self, scorer: Scorer, see: LidarObserver, decide_steps: int):
        self.scorer, self.see, self.decide_steps = scorer, see, decide_steps

    def bind(self, env) -> None:
        self.env = env

    def reset(self) -> None:
        self.see.reset(None)

    def __call__(self, obs, t: int) -> np.ndarray:
        x = np.concatenate([self.see(self.env), np.eye(self.decide_steps, dtype=np.float32)[t]])
        with torch.no_grad():
            return self.scorer(torch.from_numpy(x[None])).numpy()[0]

    def note_action(self, action) -> None:
        # the chooser acts in our controls; the view records them as the Kim action that asks for them
        self.see.note_action(kim_action_for(action, self.env.ego.v))


def chooser_policy(
    see: LidarObserver, scorer: Scorer, decide_steps: int, margin: float, moves: list[Manoeuvre], name: str
) -> ManoeuvreChooser:
    """The fitted scorer as a policy of the evaluation's interface."""
    scores = LidarScores(scorer, see, decide_steps)
    return ManoeuvreChooser(
        moves, scores, decide_steps, margin, name, reset_scorer=scores.reset, note_action=scores.note_action
    )


def policy(state: dict, name: str) -> ManoeuvreChooser:
    """A trained chooser's checkpoint as a policy, with the view and candidates it was trained with."""
    moves = [Manoeuvre(**m) for m in state["candidates"]]
    scorer = Scorer(state["inputs"], len(moves), state["hidden"])
    scorer.load_state_dict(state["scorer"])
    see = LidarObserver(False, state["lidar_scans"], state["lidar_rays"], state["lidar_speed"])
    return chooser_policy(see, scorer.eval(), state["decide_steps"], state["margin"], moves, name)
