"""Does Chae's noisy 15-value state hold what the bars ask for, and does Eq. 8 prefer it? ``envs.chae.
ClosingSpeedBraking`` (a hand-written rule on exactly what ``dqn_chae`` sees) at several thresholds, beside the
privileged scripted policies and, if asked, seed ensembles of trained runs, on one validation draw.

    python -m experiments.chae_detector --thresholds 1.0 1.25 1.5 [--readings 5] [--draw 99] [--trials 200] \
        [--run runs/NAME --ensembles 0,1,2 3,4,5 [--noise-m 0.1]] [--ttcs 1.5 1.7 1.9] [--save returns.npz]

The rule fits a line to the pedestrian's lateral distance over the last ``--readings`` readings of the agent's
view (``--rule-noise-m``, default 0.1 m) and brakes fully, from then on, once the pedestrian closes in faster
than the threshold (m/s).
Every policy drives the same trials (``chae.system.bank``; draw 99 is checkpoint selection's, 2017 the
default validation draw) in the training env, which ends at the first bump. Prints per policy the bump rate at TTC
1.5, 1.7, 1.9 s, Scenario 2's needless stops, and the mean Eq. 8 return per trial as training counts it, so that
a rule inside the bars can be set beside what the learner is paid to do. ``evaluate.family=chae`` drives the
chosen threshold as ``closing_braking`` (docs/results/chae/README.md). ``--noise-m`` makes the ensembles act on
another noise than their checkpoints record (does Eq. 8 on the noisy state prefer what the
exact-trained ensembles do there?); ``--save`` keeps every policy's per-trial returns, in bank order, for paired
comparisons across runs on the same draw:

    python -m experiments.chae_detector --compare runs/a.npz runs/b.npz --group "chaeexact*" --against "chaevote*"

prints the scenario-weighted mean return of every saved policy, and the paired difference between the mean of
the policies matching ``--group`` and the mean of those matching ``--against`` (per trial, so the same pedestrian
and the same noise), with a 95 % bootstrap interval resampling trials within each scenario.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from worldmodel.banks import validation_draw

TTCS = [1.5, 1.7, 1.9]


def drive(env, policy, entries, ttcs=TTCS) -> dict:
    """Bump % per TTC, needless stops %, the per-trial Eq. 8 returns of ``policy`` over ``entries`` and their mean,
    both scenarios weighted equally as in training (each TTC of Scenario 1 equally within it)."""
    from tqdm import tqdm

    from envs.rollout import rollout

    bumps: dict[float, list[int]] = {t: [] for t in ttcs}
    stops, returns, scenarios = [], [], []
    for scenario, spec in tqdm(entries, desc=policy.name, unit="trial", leave=False):
        o = rollout(env, policy, spec).outcome
        returns.append(o["return_chae"])
        scenarios.append(scenario)
        if scenario == 1:
            bumps[min(ttcs, key=lambda t: abs(t - spec.ttc))].append(int(o["bumped"]))
        else:
            stops.append(o["end"] == "stop")
    returns, scenarios = np.asarray(returns), np.asarray(scenarios)
    by_scenario = [float(returns[scenarios == k].mean()) for k in (1, 2)]
    return {
        "bump": [100 * float(np.mean(bumps[t])) for t in ttcs],
        "stops": 100 * float(np.mean(stops)),
        "return": float(np.mean(by_scenario)),
        "return_by_scenario": by_scenario,
        "returns": returns,
    }


def weighted_mean(returns: np.ndarray, scenario: np.ndarray) -> float:
    """Scenario 1 and Scenario 2 weighted equally, as training draws them."""
    return float(np.mean([returns[scenario == k].mean() for k in (1, 2)]))


def compare(paths: list[Path], group: str, against: str, resamples: int = 10_000) -> None:
    """Print every saved policy's weighted mean return and the paired group difference with its bootstrap interval."""
    from fnmatch import fnmatch

    scenario, returns = None, {}
    for path in paths:
        with np.load(path) as saved:
            if scenario is not None and not np.array_equal(scenario, saved["scenario"]):
                raise SystemExit(f"{path} holds another bank than {paths[0]}: compare runs on the same draw and trials")
            scenario = saved["scenario"]
            returns.update({k: saved[k] for k in saved.files if k != "scenario"})
    print("| policy | mean Eq. 8 return |\n|---|---:|")
    for name, r in returns.items():
        print(f"| {name} | {weighted_mean(r, scenario):.3f} |")
    chosen = {side: [n for n in returns if fnmatch(n, pattern)] for side, pattern in (("a", group), ("b", against))}
    if not chosen["a"] or not chosen["b"]:
        raise SystemExit(f"no saved policy matches {group!r} or {against!r}; saved: {sorted(returns)}")
    diff = np.mean([returns[n] for n in chosen["a"]], axis=0) - np.mean([returns[n] for n in chosen["b"]], axis=0)
    rng = np.random.default_rng(0)
    strata = [np.flatnonzero(scenario == k) for k in (1, 2)]
    boot = [np.mean([diff[rng.choice(idx, idx.size)].mean() for idx in strata]) for _ in range(int(resamples))]
    lo, hi = np.percentile(boot, [2.5, 97.5])
    print(
        f"\n{group} minus {against} ({len(chosen['a'])} against {len(chosen['b'])} policies): "
        f"{weighted_mean(diff, scenario):+.3f} [{lo:+.3f}, {hi:+.3f}] (95 %, {resamples} resamples)"
    )


def trained_ensembles(run: Path, groups: list[str], noise_m: float | None = None) -> list:
    """The mean-Q ensembles of ``run``'s dqn_chae seeds, one per comma-separated group, at their chosen checkpoints,
    acting on the noise their checkpoints record or on ``noise_m``."""
    import torch

    from worldmodel import artifacts
    from worldmodel.config import compose
    from worldmodel.families.chae import system as chae

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
        see = members[0].see if noise_m is None else chae.HistoryObserver(noise_m)
        name = f"{run.name} ensemble {group}" + ("" if noise_m is None else f" acting at {noise_m:g} m")
        out.append(chae.DQNPolicy(name, chae.QEnsemble(m.agent for m in members), see, 0))
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--thresholds", type=float, nargs="*", default=[], help="closing speeds, m/s")
    parser.add_argument("--readings", type=int, default=5, help="readings the line is fitted to (2..5)")
    parser.add_argument("--draw", type=validation_draw, default=99, help="bank seed (99: agent.chae.select's)")
    parser.add_argument("--trials", type=int, default=200, help="per TTC and in Scenario 2")
    parser.add_argument("--run", type=Path, help="runs/NAME holding agent_chae_dqn_chae/seedK, for --ensembles")
    parser.add_argument("--ensembles", nargs="*", default=[], help="seed groups such as 0,1,2 (with --run)")
    parser.add_argument("--noise-m", type=float, default=None, help="the ensembles act on this state noise, m")
    parser.add_argument("--rule-noise-m", type=float, default=0.1, help="the closing-speed rules' state noise, m")
    parser.add_argument("--ttcs", type=float, nargs="+", default=TTCS, help="Scenario 1's TTCs, s")
    parser.add_argument("--scripted", nargs="*", default=["braking", "latest_safe_braking"], help="scripted policies")
    parser.add_argument("--save", type=Path, help="write every policy's per-trial returns here (.npz)")
    parser.add_argument("--compare", type=Path, nargs="+", help="saved .npz files: compare them instead of driving")
    parser.add_argument("--group", default="*exact*", help="with --compare: the policies whose mean is compared")
    parser.add_argument("--against", default="*vote*", help="with --compare: the policies it is compared against")
    args = parser.parse_args(argv)
    if args.compare:
        return compare(args.compare, args.group, args.against)
    if args.ensembles and args.run is None:
        raise SystemExit("--ensembles needs --run runs/NAME")

    from envs.chae import ClosingSpeedBraking
    from worldmodel.config import compose
    from worldmodel.families.chae import system as chae

    try:
        rules = [ClosingSpeedBraking(t, args.readings, args.rule_noise_m) for t in args.thresholds]
    except ValueError as e:
        raise SystemExit(str(e)) from None
    for rule in rules:
        rule.name = f"closing > {rule.threshold_ms:g} m/s, {args.readings} readings, {args.rule_noise_m:g} m"
    policies = [chae.SCRIPTED[name]() for name in args.scripted] + rules
    policies += trained_ensembles(args.run, args.ensembles, args.noise_m) if args.ensembles else []
    cfg = compose("evaluate", ["evaluate.family=chae"])
    entries = chae.bank(SimpleNamespace(seed=args.draw, trials=args.trials, ttcs=args.ttcs))
    env = chae.family_env(cfg, camera=False)  # ends at the first bump, as in training: Eq. 8's return as learnt
    print(f"draw {args.draw}, {args.trials} trials per TTC and in Scenario 2\n")
    at = " / ".join(f"{t:g}" for t in args.ttcs)
    print(f"| policy | bumps % at TTC {at} s | needless stops % | mean Eq. 8 return (Scenario 1 / 2) |")
    print("|---|---|---:|---:|")
    saved = {}
    for policy in policies:
        s = drive(env, policy, entries, args.ttcs)
        saved[policy.name] = s["returns"]
        bumps = " / ".join(f"{b:.1f}" for b in s["bump"])
        one, two = s["return_by_scenario"]
        print(f"| {policy.name} | {bumps} | {s['stops']:.1f} | {s['return']:.3f} ({one:.3f} / {two:.3f}) |", flush=True)
    env.close()
    if args.save:
        np.savez(args.save, scenario=np.array([k for k, _ in entries]), **saved)


if __name__ == "__main__":
    main()
