"""Does Chae's noisy 15-value state hold what the bars ask for, and does Eq. 8 prefer it? ``envs.chae.
ClosingSpeedBraking`` (a hand-written rule on exactly what ``dqn_chae`` sees) at several thresholds, beside the
privileged scripted policies and, if asked, seed ensembles of trained runs, on one validation draw.

    python -m experiments.chae_detector --thresholds 1.0 1.25 1.5 [--readings 5] [--draw 99] [--trials 200] \
        [--run runs/NAME --ensembles 0,1,2 3,4,5]

The rule fits a line to the pedestrian's lateral distance over the last ``--readings`` readings of the agent's
view (0.1 m noise) and brakes fully, from then on, once the pedestrian closes in faster than the threshold (m/s).
Every policy drives the same trials (``peers.chae.bank``; draw 99 is checkpoint selection's, 2017 the test draw:
do not choose on it) in the training env, which ends at the first bump. Prints per policy the bump rate at TTC
1.5, 1.7, 1.9 s, Scenario 2's needless stops, and the mean Eq. 8 return per trial as training counts it, so that
a rule inside the bars can be set beside what the learner is paid to do. ``evaluate.family=chae`` drives the
chosen threshold as ``closing_braking`` (docs/results/chae/README.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

import numpy as np

TTCS = [1.5, 1.7, 1.9]


def drive(env, policy, entries) -> dict:
    """Bump % per TTC, needless stops % and the mean Eq. 8 return of ``policy`` over ``entries``."""
    from tqdm import tqdm

    from envs.rollout import rollout

    bumps: dict[float, list[int]] = {t: [] for t in TTCS}
    stops, returns = [], []
    for scenario, spec in tqdm(entries, desc=policy.name, unit="trial", leave=False):
        o = rollout(env, policy, spec).outcome
        returns.append(o["return_chae"])
        if scenario == 1:
            bumps[min(TTCS, key=lambda t: abs(t - spec.ttc))].append(int(o["bumped"]))
        else:
            stops.append(o["end"] == "stop")
    return {
        "bump": [100 * float(np.mean(bumps[t])) for t in TTCS],
        "stops": 100 * float(np.mean(stops)),
        "return": float(np.mean(returns)),
    }


def trained_ensembles(run: Path, groups: list[str]) -> list:
    """The mean-Q ensembles of ``run``'s dqn_chae seeds, one per comma-separated group, at their chosen checkpoints."""
    import torch

    from worldmodel import artifacts
    from worldmodel.config import compose
    from worldmodel.peers import chae

    torch.set_num_threads(1)
    run = run.resolve()
    cfg = compose("evaluate", [f"experiment={run.name}", f"paths.runs={run}", "evaluate.family=chae"])
    agents = {a.seed: a for a in artifacts.trained_agents(cfg, family="chae") if a.variant == "dqn_chae"}
    out = []
    for group in groups:
        seeds = [int(s) for s in group.split(",")]
        missing = [s for s in seeds if s not in agents]
        if missing:
            raise SystemExit(f"{run} has no dqn_chae runs for seeds {missing}; it has {sorted(agents)}")
        members = [chae.load_policy(cfg, agents[s]) for s in seeds]
        out.append(chae.DQNPolicy(f"ensemble {group}", chae.QEnsemble(m.agent for m in members), members[0].see, 0))
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--thresholds", type=float, nargs="+", required=True, help="closing speeds, m/s")
    parser.add_argument("--readings", type=int, default=5, help="readings the line is fitted to (2..5)")
    parser.add_argument("--draw", type=int, default=99, help="bank seed (99: agent.select's; 2017 is the test draw)")
    parser.add_argument("--trials", type=int, default=200, help="per TTC and in Scenario 2")
    parser.add_argument("--run", type=Path, help="runs/NAME holding agent_chae_dqn_chae/seedK, for --ensembles")
    parser.add_argument("--ensembles", nargs="*", default=[], help="seed groups such as 0,1,2 (with --run)")
    args = parser.parse_args(argv)
    if args.ensembles and args.run is None:
        raise SystemExit("--ensembles needs --run runs/NAME")

    from envs.chae import ClosingSpeedBraking
    from worldmodel.config import compose
    from worldmodel.peers import chae

    try:
        rules = [ClosingSpeedBraking(t, args.readings) for t in args.thresholds]
    except ValueError as e:
        raise SystemExit(str(e)) from None
    for rule in rules:
        rule.name = f"closing speed > {rule.threshold_ms:g} m/s"
    policies = [chae.SCRIPTED[name]() for name in ("braking", "latest_safe_braking")] + rules
    policies += trained_ensembles(args.run, args.ensembles) if args.ensembles else []
    cfg = compose("evaluate", ["evaluate.family=chae"])
    entries = chae.bank(SimpleNamespace(seed=args.draw, trials=args.trials, ttcs=TTCS))
    env = chae.family_env(cfg, camera=False)  # ends at the first bump, as in training: Eq. 8's return as learnt
    print(f"{args.readings} readings, draw {args.draw}, {args.trials} trials per TTC and in Scenario 2\n")
    print("| policy | bumps % at TTC 1.5 / 1.7 / 1.9 s | needless stops % | mean Eq. 8 return |")
    print("|---|---|---:|---:|")
    for policy in policies:
        s = drive(env, policy, entries)
        bumps = " / ".join(f"{b:.1f}" for b in s["bump"])
        print(f"| {policy.name} | {bumps} | {s['stops']:.1f} | {s['return']:.3f} |", flush=True)
    env.close()


if __name__ == "__main__":
    main()
