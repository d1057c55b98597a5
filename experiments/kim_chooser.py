"""The chooser on Kim's junction, from the LIDAR: learn what each manoeuvre would cost, not what the planner did.

    python -m experiments.kim_chooser labels [--episodes 1500] [--out runs/kim_chooser/train.npz] OVERRIDES...
    python -m experiments.kim_chooser labels --bank --out runs/kim_chooser/bank77.npz evaluate.kim.seed=77
    python -m experiments.kim_chooser fit [--data FILE] [--bank FILE] [--margin 0.0] seed=0
    python -m experiments.kim_chooser drive [--data FILE] [--margin 0.0] evaluate.kim.seed=77 seed=0
    python -m experiments.kim_chooser compare evaluate.kim.seed=77
    python -m experiments.kim_chooser ceiling --data runs/kim_chooser/bank77_decide1.0.npz

The cloned LIDAR students stop at straight-line braking because the planner's choices, rare swerves that flicker
from step to step, are what they cannot copy (docs/results/kim/README.md). The chooser (``envs/chooser.py``,
docs/design.md §5) learns the exact cost of every candidate manoeuvre instead and, because it brakes until it
switches once, decides only in braking's own states, which the labels hold exactly.

``labels``: straight-line braking through ``--episodes`` training-distribution episodes (``KIM_CHOOSER_LABELS``,
apart from the training's and the students'), or through the evaluation's bank (``--bank``, ``evaluate.kim.*``);
at each of the first ``--decide-s`` seconds the LIDAR view the agent would see and, by re-simulation, the exact cost
(Kim's ``kim_unaware``: the summed ISS of the crashes to come, 0 when nothing is hit) of starting each candidate
there.

``fit``: an MLP regresses all candidates' costs from the view and the decision step, by least squares, on the
first 85 % of the training labels; the epoch kept is the one whose chooser avoids most on the last 15 %. Because
the decisions happen in labelled states, a rule's outcome is known without simulating: braking's cost if it never
switches, else the chosen candidate's exact cost where it switched. Reports that for braking, the learned chooser
and the exact-cost chooser (the same rule on the true costs: the ceiling of these candidates) on the held-out
episodes and, with ``--bank``, on the bank's labels.

``drive``: the fitted chooser drives the bank in closed loop beside straight-line braking (the offline numbers of
``fit --bank`` must come out the same: the LIDAR is noise-free) and writes both policies' per-trial avoidance and
ISS beside ``--data``. ``compare``: the seeds of ``drive`` pooled, and the paired test against braking.
``ceiling``: on labels of a long window (``labels --decide-s 1.0``), the exact-cost chooser kept to each shorter one.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from envs.chooser import BRAKE, ManoeuvreChooser, decide_steps_for, switch_choice
from envs.kim import SCENARIOS, kim_action_for
from envs.planner import Manoeuvre, _Plan, plan_cost
from envs.streams import KIM_CHOOSER_LABELS
from worldmodel import stats
from worldmodel.common import set_threads
from worldmodel.config import compose
from worldmodel.peers import kim

from .kim_student import beside_braking

HELD_OUT = 0.15
REWARD = "kim_unaware"
STEP_S = 0.1  # the family's steps (kim.family_env)


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


def labels(cfg, specs: list, decide_steps: int) -> dict:
    env = kim.family_env(cfg, REWARD)
    twin = env.planning_twin()
    see = kim.observer(cfg, REWARD)
    moves = candidates(env.step_s)
    view, cost, episode, step = [], [], [], []
    for e, spec in enumerate(tqdm(specs, desc="braking, every candidate costed", unit="episode")):
        env.reset(options={"scenario": spec})
        see.reset(None)
        for t in range(decide_steps):
            snap = env.snapshot()
            view.append(see(env))
            cost.append([plan_cost(twin, snap, _Plan(m, t), reward=REWARD) for m in moves])
            episode.append(e)
            step.append(t)
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
    }


def window(data: dict, decide_steps: int) -> dict:
    """Labels of a longer decision window cut to the first ``decide_steps`` steps; a shorter one is refused."""
    longest = int(data["step"].max()) + 1
    if longest < decide_steps:
        raise SystemExit(f"these labels hold {longest} decision steps, --decide-s asks for {decide_steps}: relabel")
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


def report(name: str, data: dict, predicted: np.ndarray | None, margin: float = 0.0) -> None:
    """Braking, the chooser on ``predicted`` costs (if given) and on the exact ones, from the labels alone."""
    c, ep = data["cost"].astype(np.float64), data["episode"]
    rules = [("braking", np.zeros_like(c)), ("learned chooser", predicted), ("exact-cost chooser", c)]
    for who, scores in [(who, s) for who, s in rules if s is not None]:
        res = outcomes(c, scores, ep, margin if who == "learned chooser" else 0.0)
        low, high = stats.wilson(int((res == 0).sum()), len(res))
        print(
            f"{name}: {who}: avoided {100 * np.mean(res == 0):.1f} % [{low:.0f}, {high:.0f}] of {len(res)}; "
            f"injury {-res.mean():.2f}"
        )


class Scorer(nn.Module):
    def __init__(self, inputs: int, outputs: int, hidden: int = 256):
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(inputs, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, outputs)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


def fit(train: dict, decide_steps: int, seed: int, margin: float, epochs: int = 60) -> Scorer:
    torch.manual_seed(seed)
    x, y, ep = features(train, decide_steps), train["cost"], train["episode"]
    held = ep >= np.quantile(np.unique(ep), 1.0 - HELD_OUT)
    xs, ys = torch.from_numpy(x[~held]), torch.from_numpy(y[~held])
    scorer = Scorer(x.shape[1], y.shape[1])
    opt = torch.optim.Adam(scorer.parameters(), lr=1e-3)
    rng = np.random.default_rng(seed)
    held_data = {k: v[held] for k, v in train.items()}
    best, best_state = -1.0, None
    for epoch in range(epochs):
        for idx in np.array_split(rng.permutation(len(xs)), max(1, len(xs) // 128)):
            loss = ((scorer(xs[idx]) - ys[idx]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        with torch.no_grad():
            pred = scorer(torch.from_numpy(x[held])).numpy()
        avoided = np.mean(outcomes(held_data["cost"], pred, held_data["episode"], margin) == 0)
        if avoided > best:
            best, best_state = avoided, {k: v.clone() for k, v in scorer.state_dict().items()}
            best_epoch = epoch
    scorer.load_state_dict(best_state)
    print(f"kept epoch {best_epoch + 1} of {epochs}: the chooser avoids {100 * best:.1f} % of the held-out episodes")
    with torch.no_grad():
        report("held out", held_data, scorer(torch.from_numpy(x[held])).numpy(), margin)
    return scorer


class LidarScores:
    """The fitted scorer behind ``ManoeuvreChooser``: the LIDAR view at each decision step, as labelled."""

    def __init__(self, scorer: Scorer, see, decide_steps: int):
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


def chooser_policy(cfg, scorer: Scorer, decide_steps: int, margin: float, step_s: float) -> ManoeuvreChooser:
    """The fitted scorer as a policy of the evaluation's interface."""
    scores = LidarScores(scorer, kim.observer(cfg, REWARD), decide_steps)
    return ManoeuvreChooser(
        candidates(step_s), scores, decide_steps, margin, f"chooser_seed{int(cfg.seed)}",
        reset_scorer=scores.reset, note_action=scores.note_action,
    )  # fmt: skip


def drive(cfg, scorer: Scorer, decide_steps: int, margin: float, out_dir: Path) -> None:
    beside_braking(cfg, chooser_policy(cfg, scorer, decide_steps, margin, STEP_S), out_dir)


def ceiling(data: dict) -> None:
    """The exact-cost chooser on labels of a long window, kept to each shorter window: how the ceiling grows with
    the time the chooser may take to switch."""
    c, ep, step = data["cost"].astype(np.float64), data["episode"], data["step"]
    for last in range(1, int(step.max()) + 2):
        keep = step < last
        avoided = np.mean(outcomes(c[keep], c[keep], ep[keep], 0.0) == 0)
        print(f"may switch within {last * STEP_S:.1f} s: the exact-cost chooser avoids {100 * avoided:.1f} %")


def compare(cfg, out_dir: Path) -> None:
    """The seeds of ``drive`` pooled, and the paired test against braking on the same trials, seed by seed."""
    draw = cfg.evaluate.kim.seed
    files = sorted(out_dir.glob(f"drive_chooser_seed*_draw{draw}.csv"))
    braking_file = out_dir / f"drive_braking_draw{draw}.csv"
    if not files or not braking_file.exists():
        raise SystemExit(f"no drive_chooser_seed*_draw{draw}.csv or {braking_file.name} in {out_dir}: run drive first")
    chooser = np.concatenate([np.loadtxt(f, delimiter=",", ndmin=2) for f in files])
    braking = np.tile(np.loadtxt(braking_file, delimiter=",", ndmin=2), (len(files), 1))
    trials = int(cfg.evaluate.kim.trials)  # the bank holds each scenario's trials in a block, in SCENARIOS' order
    if len(braking) != len(files) * trials * len(SCENARIOS):
        raise SystemExit(f"the files hold {len(braking) // len(files)} trials, evaluate.kim.trials={trials} says more")
    for who, rows in (("braking", braking[: len(braking) // len(files)]), (f"chooser, {len(files)} seeds", chooser)):
        low, high = stats.wilson(int(rows[:, 0].sum()), len(rows))
        scenario = np.arange(len(rows)) // trials % len(SCENARIOS)
        each = " / ".join(f"{100 * rows[scenario == k, 0].mean():.1f}" for k in range(len(SCENARIOS)))
        print(
            f"{who}: avoided {100 * rows[:, 0].mean():.1f} % [{low:.0f}, {high:.0f}] of {len(rows)} "
            f"({' / '.join(SCENARIOS)}: {each}); injury {-rows[:, 1].mean():.2f}"
        )
    p = stats.paired_permutation_p(chooser[:, 1], braking[:, 1])
    print(f"paired by seed and trial, ISS chooser against braking: p = {p:.4f}")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("command", choices=("labels", "fit", "drive", "compare", "ceiling"))
    parser.add_argument("--episodes", type=int, default=1500, help="labels: training-distribution episodes")
    parser.add_argument("--bank", nargs="?", const=True, default=None, help="labels: the bank; fit: its labels")
    parser.add_argument("--out", "--data", dest="data", type=Path, default=Path("runs/kim_chooser/train.npz"))
    parser.add_argument("--decide-s", type=float, default=0.3, help="seconds in which the chooser may switch")
    parser.add_argument("--margin", type=float, default=0.0, help="predicted ISS by which a switch must win")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. evaluate.kim.seed=77 seed=0")
    args = parser.parse_intermixed_args(argv)
    cfg = compose("train_agent", ["agent=ddpg_kim", *args.overrides])
    set_threads(1)
    decide_steps = decide_steps_for(args.decide_s, STEP_S)
    if args.command == "labels":
        if args.bank:
            specs = kim.bank(cfg.evaluate.kim)
        else:
            specs = [kim.training_scenario(cfg, KIM_CHOOSER_LABELS, e) for e in range(args.episodes)]
        data = labels(cfg, specs, decide_steps)
        args.data.parent.mkdir(parents=True, exist_ok=True)
        np.savez(args.data, **data)
        report("these labels", data, None)
        print(f"wrote {args.data}: {len(data['view'])} decision states of {len(specs)} episodes")
        return
    if args.command == "compare":
        compare(cfg, args.data.parent)
        return
    if args.command == "ceiling":
        ceiling(dict(np.load(args.data)))
        return
    train = window(dict(np.load(args.data)), decide_steps)
    scorer = fit(train, decide_steps, int(cfg.seed), args.margin)
    if args.command == "fit" and isinstance(args.bank, str):
        bank = window(dict(np.load(args.bank)), decide_steps)
        with torch.no_grad():
            report(
                f"bank {args.bank}", bank, scorer(torch.from_numpy(features(bank, decide_steps))).numpy(), args.margin
            )
    if args.command == "drive":
        drive(cfg, scorer, decide_steps, args.margin, args.data.parent)


if __name__ == "__main__":
    main()
