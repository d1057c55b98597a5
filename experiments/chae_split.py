"""Where an ensemble and its members part at the corner: each step's greedy brake levels of the members beside the
ensemble's, on one TTC of a validation draw, and what they were in the trials the ensemble bumps in.

    python -m experiments.chae_split runs/NAME --seeds 21 22 23 --draw 105 [--trials 1000] [--ttc 1.5] [--average vote]

A diagnostic (docs/results/chae/notes/ensembles.md): a vote of members that each bump in
0.8-1.3 % alone bumped in 2.8 %. For every Scenario-1 trial at ``--ttc`` this drives the ensemble and records, at
each step, every member's greedy level and the ensemble's; it prints how the members split over the steps of the
trials that bump and of those that do not, and in how many bumping trials some member wanted a harder brake than the
ensemble chose before the first step it braked fully.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from worldmodel.banks import validation_draw

from .chae_margin import VoteEnsemble

FULL = 0  # the index of -9.8 m/s^2 in envs.chae.BRAKE_LEVELS (levels are ordered hardest first)


class Recording:
    """The ensemble acting as usual, with each step's member levels and its own level kept for the current trial."""

    def __init__(self, ensemble):
        self.ensemble, self.steps = ensemble, []

    def act(self, obs, step=None, explore: bool = False) -> int:
        chosen = self.ensemble.act(obs)
        members = [int(np.argmax(m.q_values(obs))) for m in self.ensemble.members]
        self.steps.append((members, chosen))
        return chosen


def split(members: list[int]) -> str:
    """'agree', '2-1' or '1-1-1' for three members (the number of distinct levels chosen)."""
    return {1: "agree", 2: "2-1", 3: "1-1-1"}[len(set(members))]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="runs/NAME, holding agent_chae_dqn_chae/seedK")
    parser.add_argument("--seeds", type=int, nargs=3, required=True, help="the ensemble's three members")
    parser.add_argument("--draw", type=validation_draw, required=True, help="bank seed, a validation draw")
    parser.add_argument("--trials", type=int, default=1000)
    parser.add_argument("--ttc", type=float, default=1.5)
    parser.add_argument("--average", choices=("q", "vote"), default="vote")
    args = parser.parse_args(argv)

    from experiments.chae_margin import load_members
    from worldmodel.families.chae import system as chae

    cfg, members = load_members(args.run, args.seeds)
    combine = VoteEnsemble if args.average == "vote" else chae.QEnsemble
    recording = Recording(combine(m.agent for m in members))
    policy = chae.DQNPolicy("split", recording, members[0].see, 0)
    entries = [e for e in chae.bank(SimpleNamespace(seed=args.draw, trials=args.trials, ttcs=[args.ttc])) if e[0] == 1]
    env = chae.family_env(cfg, camera=False, end_on_bump=False)
    counts = {True: {"agree": 0, "2-1": 0, "1-1-1": 0}, False: {"agree": 0, "2-1": 0, "1-1-1": 0}}
    trials = {True: 0, False: 0}
    overruled = (
        0  # bumping trials where a member wanted a harder level than the ensemble's before it first braked fully
    )
    for entry in entries:
        recording.steps = []
        (row,) = chae.run_policy(env, policy, [entry], leave=False)
        bumped = bool(row["bump"])
        trials[bumped] += 1
        first_full = next((i for i, (_, c) in enumerate(recording.steps) if c == FULL), len(recording.steps))
        for ms, _ in recording.steps[:first_full]:
            counts[bumped][split(ms)] += 1
        if bumped and any(min(ms) < c for ms, c in recording.steps[:first_full]):
            overruled += 1
    env.close()
    print(
        f"seeds {args.seeds}, draw {args.draw}, TTC {args.ttc:g} s, {len(entries)} Scenario-1 trials, {args.average}\n"
    )
    print("| trials | n | steps before full braking: members agree / 2-1 / 1-1-1 |\n|---|---:|---|")
    for bumped in (True, False):
        c = counts[bumped]
        total = max(sum(c.values()), 1)
        shares = " / ".join(f"{100 * c[k] / total:.1f} %" for k in ("agree", "2-1", "1-1-1"))
        print(f"| {'bumped' if bumped else 'no bump'} | {trials[bumped]} | {shares} |")
    print(f"\nbumping trials where a member wanted a harder level before the ensemble braked fully: {overruled}")


if __name__ == "__main__":
    main()
