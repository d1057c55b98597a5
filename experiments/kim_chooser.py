"""Research on the LIDAR chooser of Kim's junction (agent=kim_chooser, worldmodel/families/kim/chooser.py): its labels
on the evaluation's bank, offline fits, its ceiling.

    python -m experiments.kim_chooser labels [--episodes N] [--out runs/kim_chooser/train.npz] OVERRIDES...
    python -m experiments.kim_chooser labels --bank --out runs/kim_chooser/bank77.npz evaluate.kim.seed=77
    python -m experiments.kim_chooser fit [--data FILE] [--bank FILE] [--margin M] seed=0
    python -m experiments.kim_chooser drive [--data FILE] [--margin M] evaluate.kim.seed=77 seed=0
    python -m experiments.kim_chooser compare evaluate.kim.seed=77
    python -m experiments.kim_chooser ceiling --data runs/kim_chooser/bank77_decide1.0.npz

The agent itself trains with ``python -m worldmodel.train_agent agent=kim_chooser`` and is evaluated beside the
family's other policies by ``python -m worldmodel.evaluate evaluate.family=kim``. This script keeps what that does
not: labels of other episodes and windows in files of their own, and the chooser judged on them offline.

``labels``: straight-line braking through ``--episodes`` training-distribution episodes (the agent's stream,
seeded by ``seed``), or through the evaluation's bank (``--bank``, ``evaluate.kim.*``); at each of the first
``--decide-s`` seconds the LIDAR view and every candidate's exact cost there.

``fit``: the agent's fit (the epoch kept is the one whose chooser avoids most on the last 15 % of the labelled
episodes) on ``--data``; reports braking, the learned chooser and the exact-cost chooser (the same rule on the true
costs: the ceiling of these candidates) on the held-out episodes and, with ``--bank``, on the bank's labels, from
the labels alone: the chooser decides only in labelled states, so a rule's outcome is known without simulating.

``drive``: the fitted chooser drives the bank in closed loop beside straight-line braking (the offline numbers of
``fit --bank`` must come out the same: the LIDAR is noise-free) and writes both policies' per-trial avoidance and
ISS beside ``--data``. ``compare``: the seeds of ``drive`` pooled, and the paired test against braking.
``ceiling``: on labels of a long window (``labels --decide-s 1.0``), the exact-cost chooser kept to each shorter one.

``--episodes``, ``--decide-s`` and ``--margin`` default to the agent's (``agent.kim_chooser.*``,
conf/agent/kim_chooser.yaml).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from envs.chooser import decide_steps_for
from envs.kim import SCENARIOS
from envs.streams import KIM_CHOOSER_LABELS
from worldmodel import stats
from worldmodel.common import set_threads
from worldmodel.config import compose
from worldmodel.families.kim import system as kim
from worldmodel.families.kim.chooser import (
    REWARD,
    Scorer,
    candidates,
    chooser_policy,
    features,
    fit,
    held_out,
    label_episodes,
    outcomes,
    window,
)

from .kim_student import beside_braking

STEP_S = 0.1  # the family's steps (kim.family_env)


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


def drive(cfg, scorer: Scorer, decide_steps: int, margin: float, out_dir: Path) -> None:
    see = kim.observer(cfg, REWARD)
    policy = chooser_policy(see, scorer, decide_steps, margin, candidates(STEP_S), f"chooser_seed{cfg.seed}")
    beside_braking(cfg, policy, out_dir)


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
    parser.add_argument("--episodes", type=int, help="labels: training-distribution episodes")
    parser.add_argument("--bank", nargs="?", const=True, default=None, help="labels: the bank; fit: its labels")
    parser.add_argument("--out", "--data", dest="data", type=Path, default=Path("runs/kim_chooser/train.npz"))
    parser.add_argument("--decide-s", type=float, help="seconds in which the chooser may switch")
    parser.add_argument("--margin", type=float, help="predicted ISS by which a switch must win")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. evaluate.kim.seed=77 seed=0")
    args = parser.parse_intermixed_args(argv)
    cfg = compose("train_agent", ["agent=kim_chooser", *args.overrides])
    agent = cfg.agent.kim_chooser
    episodes = agent.episodes if args.episodes is None else args.episodes
    margin = agent.margin if args.margin is None else args.margin
    set_threads(1)
    decide_steps = decide_steps_for(agent.decide_s if args.decide_s is None else args.decide_s, STEP_S)
    if args.command == "labels":
        if args.bank:
            specs = kim.bank(cfg.evaluate.kim)
        else:
            specs = [kim.training_scenario(cfg, KIM_CHOOSER_LABELS, e) for e in range(episodes)]
        data = label_episodes(cfg, specs, decide_steps)
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
    scorer, epoch, avoided = fit(train, decide_steps, cfg.seed, margin, agent.epochs, agent.hidden)
    print(f"kept epoch {epoch} of {agent.epochs}: the chooser avoids {100 * avoided:.1f} % of the held-out episodes")
    held = held_out(train["episode"])
    with torch.no_grad():
        held_data = {k: v[held] for k, v in train.items()}
        report("held out", held_data, scorer(torch.from_numpy(features(held_data, decide_steps))).numpy(), margin)
        if args.command == "fit" and isinstance(args.bank, str):
            bank = window(dict(np.load(args.bank)), decide_steps)
            report(f"bank {args.bank}", bank, scorer(torch.from_numpy(features(bank, decide_steps))).numpy(), margin)
    if args.command == "drive":
        drive(cfg, scorer, decide_steps, margin, args.data.parent)


if __name__ == "__main__":
    main()
