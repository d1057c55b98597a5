"""How thin the gap is that Chae's agents decide on: an ensemble's greedy decisions with its "no brake" value raised
by a margin, on a validation draw.

    python -m experiments.chae_margin runs/NAME --seeds 9 10 11 --margins -0.05 0 0.05 [--draw 99] [--trials 200]
        [--average q|h|vote]

Loads the runs' chosen checkpoints (``runs/NAME/agent_chae_dqn_chae/seedK``) as ``evaluate.chae.ensemble`` does,
drives the draw (``chae.system.bank``: Scenario 1 at TTC 1.5, 1.7, 1.9 s and Scenario 2) once per margin and prints a
markdown table of the highest bump rate and the needless stops (docs/results/chae/notes/ensembles.md). A margin m > 0
brakes only when braking's mean Q beats not braking's by more than m. ``--average h`` averages the members' h(Q) (the
value_rescale squashing) instead of Q; ``--average vote`` takes the members' majority action (``VoteEnsemble``),
``--average cautious`` the hardest level any member chooses . ``--noise-m`` drives with another noise on Chae's state
than the members' checkpoints record (trained on the exact state, acting on the noisy one, and the reverse).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from worldmodel.banks import validation_draw

TTCS = [1.5, 1.7, 1.9]
NO_BRAKE = 3  # the index of 0 m/s^2 in envs.chae.BRAKE_LEVELS


class MarginEnsemble:
    """The mean-Q ensemble, greedy after adding ``margin`` to the "no brake" action's value."""

    def __init__(self, ensemble, margin: float):
        self.ensemble, self.margin = ensemble, float(margin)

    def act(self, obs, step=None, explore: bool = False) -> int:
        q = self.ensemble.q_values(obs).copy()
        q[NO_BRAKE] += self.margin
        return int(np.argmax(q))


class SquashedMeanEnsemble:
    """Greedy on the mean of the members' h(Q) rather than of Q. h is increasing, so a single member acts as before;
    for several, a member's very negative Q (a feared bump) weighs less against the others than in the mean of Q."""

    def __init__(self, members):
        self.members = list(members)

    def q_values(self, obs: np.ndarray) -> np.ndarray:
        import torch

        from worldmodel.models.dqn import squash

        values = torch.as_tensor(np.stack([m.q_values(obs) for m in self.members]))
        return squash(values).mean(dim=0).numpy()


class VoteEnsemble:
    """Several trained DQNs acting as one by majority vote: each member's greedy
    brake level is one vote, the most voted level wins, and a tie goes to the level with the highest mean Q among
    the tied ones. Unlike the mean of Q, a level no member would choose alone can never win: a mean-Q ensemble of
    three runs that each stop needlessly in <= 0.9 % of Scenario 2 stopped in 14.7 % (docs/results/chae/).

    ``q_values`` returns scores whose argmax is the vote: the votes, plus the mean Q scaled into [0, 1e-3] to break
    ties (less than one vote, so it never overturns a majority)."""

    def __init__(self, members):
        self.members = list(members)

    def q_values(self, obs: np.ndarray) -> np.ndarray:
        values = np.stack([m.q_values(obs) for m in self.members])  # (members, ..., actions)
        levels = np.arange(values.shape[-1])
        votes = (values.argmax(axis=-1)[..., None] == levels).sum(axis=0).astype(float)
        mean = values.mean(axis=0)
        low = mean.min(axis=-1, keepdims=True)
        spread = np.ptp(mean, axis=-1, keepdims=True)
        return votes + 1e-3 * (mean - low) / (spread + 1e-12)


class CautiousEnsemble:
    """The hardest brake level that any member chooses greedily (levels are ordered hardest first), so that one
    member's fear at the corner is never outvoted; ``q_values`` scores that level 1 and the others 0."""

    def __init__(self, members):
        self.members = list(members)

    def q_values(self, obs: np.ndarray) -> np.ndarray:
        values = np.stack([m.q_values(obs) for m in self.members])
        scores = np.zeros(values.shape[-1])
        scores[values.argmax(axis=-1).min()] = 1.0
        return scores


def load_members(run: Path, seeds: list[int]):
    """The evaluate config for ``runs/NAME`` and its dqn_chae runs' chosen checkpoints for ``seeds``, on one thread."""
    import torch

    from worldmodel import artifacts
    from worldmodel.config import compose
    from worldmodel.families.chae import system as chae

    torch.set_num_threads(1)
    run = run.resolve()
    cfg = compose("evaluate", [f"experiment={run.name}", f"paths.runs={run}", "evaluate.family=chae"])
    agents = {a.seed: a for a in artifacts.trained_agents(cfg, family="chae") if a.variant == "dqn_chae"}
    missing = [s for s in seeds if s not in agents]
    if missing:
        raise SystemExit(f"{run} has no dqn_chae runs for seeds {missing}; it has {sorted(agents)}")
    return cfg, [chae.load_policy(cfg, agents[s]) for s in seeds]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="runs/NAME, holding agent_chae_dqn_chae/seedK")
    parser.add_argument("--seeds", type=int, nargs="+", required=True, help="the ensemble's members")
    parser.add_argument("--margins", type=float, nargs="+", required=True)
    parser.add_argument("--draw", type=validation_draw, default=99, help="bank seed (99: agent.chae.select's)")
    parser.add_argument("--trials", type=int, default=200, help="per TTC and in Scenario 2")
    parser.add_argument("--ttcs", type=float, nargs="+", default=TTCS, help="Scenario 1's TTCs, s")
    parser.add_argument(
        "--average",
        choices=("q", "h", "vote", "cautious"),
        default="q",
        help="average Q (as evaluate does) or h(Q), vote, or take the hardest level any member chooses",
    )
    parser.add_argument(
        "--noise-m",
        type=float,
        default=None,
        help="drive with this noise (m) on Chae's state instead of the one the members were trained with",
    )
    args = parser.parse_args(argv)

    from worldmodel.families.chae import system as chae

    cfg, members = load_members(args.run, args.seeds)
    average = {"q": chae.QEnsemble, "h": SquashedMeanEnsemble, "vote": VoteEnsemble, "cautious": CautiousEnsemble}[
        args.average
    ]
    ensemble = average(m.agent for m in members)
    see = members[0].see if args.noise_m is None else chae.HistoryObserver(args.noise_m)
    entries = chae.bank(SimpleNamespace(seed=args.draw, trials=args.trials, ttcs=args.ttcs))
    env = chae.family_env(cfg, camera=False, end_on_bump=False)
    print(
        f"seeds {args.seeds}, draw {args.draw}, {args.trials} trials per TTC and in Scenario 2, mean of "
        f"{ {'q': 'Q', 'h': 'h(Q)', 'vote': 'votes', 'cautious': 'the hardest level'}[args.average] }, state noise "
        f"{getattr(getattr(see, 'view', None), 'noise_m', 'n/a')} m\n"
    )
    at = " / ".join(f"{t:g}" for t in args.ttcs)
    print(f"| margin | bumps % at TTC {at} s | needless stops % |\n|---:|---|---:|")
    for m in args.margins:
        policy = chae.DQNPolicy(f"margin{m:+g}", MarginEnsemble(ensemble, m), see, 0)
        rows = chae.run_policy(env, policy, entries, leave=False)
        s = chae.summarise(rows, args.ttcs)["policies"][policy.name]
        bumps = " / ".join(f"{s['bump_rate'][t]:.1f}" for t in args.ttcs)
        print(f"| {m:+g} | {bumps} | {s['unnecessary_stop_rate']:.1f} |", flush=True)
    env.close()


if __name__ == "__main__":
    main()
