"""Does Merola's Double DQN rank its nine actions as its own returns do? (family merola)

    python -m experiments.merola_q_vs_exact experiment=NAME scale=quick [--draw 2022] [--trials 30] [--every 5]

Each trained ``ddqn_merola`` agent of the experiment drives, greedy, the first ``--trials`` trials per scenario of a
validation draw (the evaluation's bank). Every ``--every`` steps the simulator gives, for each of the nine actions,
the exact discounted return (the agent's own reward and gamma) of taking that action once and then following the
agent's greedy policy to the end: Q^pi(s, a), re-simulated on the camera-less twin. Beside it, the network's
Q(s, a). A Q-network that has learnt its own policy's values orders the actions as the re-simulated returns do
(pairwise order 1, Spearman 1); one at chance scores 0.5 and 0.

The tables are ``experiments/critic_vs_exact.py``'s, on costs = minus the returns, straight-line braking (pedal -1,
wheel straight) taken as the reference candidate; "pick - braking" is in the reward's units. The re-simulation
needs the agent's view of the twin, so only views without the camera are scored (``obs=privileged``); the others
are listed as left out. Sealed draws are refused. Writes ``runs/NAME/critic_vs_exact/merola_q_vs_exact_draw<seed>.md``
and ``.csv``.
"""

from __future__ import annotations

import argparse
import copy
import logging
from types import SimpleNamespace

import numpy as np
import torch
from tqdm import tqdm

from experiments.critic_vs_exact import Scored, matters, write_report
from worldmodel import artifacts
from worldmodel.banks import sealed_seed_problem, validation_draw
from worldmodel.config import compose, validate
from worldmodel.families.merola.system import ACTIONS, bank, family_env, load_policy, merola_action

log = logging.getLogger("merola_q_vs_exact")
BRAKING = int(np.flatnonzero((ACTIONS[:, 0] == 0.0) & (ACTIONS[:, 1] == -1.0))[0])
ORDER = [BRAKING, *(k for k in range(len(ACTIONS)) if k != BRAKING)]  # braking first, as the tables expect
MATTERS_RETURN = 1.0  # reward units: a state where some action's return beats braking's by more than this matters


def follow(twin, policy, first: int, gamma: float) -> float:
    """The discounted return on ``twin`` (restored to the state to value) of action ``first`` and then ``policy``'s
    greedy actions to the end; ``policy.see`` must already hold the view of that state."""
    ret, discount, action = 0.0, 1.0, merola_action(first)
    while True:
        obs, reward, terminated, truncated, _ = twin.step(action)
        ret += discount * float(reward)
        discount *= gamma
        if terminated or truncated:
            return ret
        policy.see.note_action(action)
        action = merola_action(policy.agent.act(policy.see(twin, obs), explore=False))


def episode_values(env, twin, policy, spec, every: int, gamma: float) -> tuple[list, list, list]:
    """Drive ``spec`` greedily; every ``every`` steps, the network's Q and the re-simulated Q^pi of each action
    (both in ``ORDER``). Returns (Q rows, Q^pi rows, steps)."""
    obs, _ = env.reset(options={"scenario": spec})
    policy.reset()
    policy.bind(env)
    q_rows, exact_rows, steps = [], [], []
    t = 0
    while True:
        x = policy.see(env, obs)
        if t % every == 0:
            snap, view = env.snapshot(), copy.deepcopy(policy.see)
            exact = []
            for a in ORDER:
                twin.restore(snap)
                rollout_policy = copy.copy(policy)
                rollout_policy.see = copy.deepcopy(view)
                exact.append(follow(twin, rollout_policy, a, gamma))
            q_rows.append(policy.agent.q_values(x)[ORDER])
            exact_rows.append(exact)
            steps.append(t)
        action = merola_action(policy.agent.act(x, explore=False))
        policy.see.note_action(action)
        obs, _, terminated, truncated, _ = env.step(action)
        t += 1
        if terminated or truncated:
            return q_rows, exact_rows, steps


def score(cfg, agent, specs, every: int) -> tuple[Scored, dict] | str:
    """One agent's Q against its re-simulated returns on ``specs``, or why it is left out."""
    policy = load_policy(cfg, agent)
    if getattr(policy.see, "camera", True):
        return f"{agent.key}: its view needs the camera, which the re-simulation does not render"
    gamma = float(policy.agent.cfg.gamma)
    env = family_env(cfg, step_s=0.1, camera=False, reward=agent.reward)
    twin = env.planning_twin()
    q, exact, episode, t = [], [], [], []
    for e, spec in enumerate(tqdm(specs, desc=agent.key, unit="trial")):
        rows_q, rows_exact, steps = episode_values(env, twin, policy, spec, every, gamma)
        q += rows_q
        exact += rows_exact
        episode += [e] * len(steps)
        t += steps
    env.close()
    costs = -np.asarray(exact, np.float64)
    val = {"costs": costs, "episode": np.asarray(episode), "t": np.asarray(t)}
    return Scored(agent.key, "DDQN -Q", -np.asarray(q, np.float64), np.arange(len(costs))), val


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. experiment=quick scale=quick")
    parser.add_argument("--draw", type=validation_draw, default=None, help="the validation draw (default: config's)")
    parser.add_argument("--trials", type=int, default=30, help="trials per scenario, the bank's first")
    parser.add_argument("--every", type=int, default=5, help="steps between valued states")
    parser.add_argument("--boot", type=int, default=2000, help="bootstrap resamples of the scenarios")
    args = parser.parse_intermixed_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(1)
    cfg = compose("train_agent", [*args.overrides, "agent=ddqn_merola"])
    typed = validate(cfg)
    draw = typed.evaluate.merola.seed if args.draw is None else args.draw
    why = sealed_seed_problem(draw)
    if why:
        parser.error(why.split(";")[0] + ": choose a validation draw (worldmodel/banks.py)")
    specs = bank(SimpleNamespace(**{**vars(typed.evaluate.merola), "seed": draw, "trials": args.trials}))
    skipped = []
    for agent in artifacts.trained_agents(cfg, family="merola"):
        result = score(cfg, agent, specs, args.every)
        if isinstance(result, str):
            skipped.append(result)
            continue
        scored, val = result
        head = [
            f"Experiment {cfg.experiment}, family merola, validation draw {draw}: {len(specs)} trials, "
            f"{len(val['costs'])} states of {agent.key} (every {args.every} steps), "
            f"{int(matters(val['costs'], MATTERS_RETURN).sum())} of them where some action's return beats braking's "
            f"by more than {MATTERS_RETURN:g}.",
            "",
            "Candidates: the nine actions, braking (pedal -1, wheel straight) first. Costs: minus the discounted "
            f"return (reward {agent.reward}) of the action and then the agent's greedy policy, re-simulated. Scores: "
            "minus the network's Q. Intervals: bootstrap 95 % over trials.",
            "",
        ]
        stem = f"merola_q_vs_exact_draw{draw}_{agent.key.replace('/', '_')}"
        units = {"matters_by": MATTERS_RETURN, "points": 1.0, "unit": "return", "margin_unit": ""}
        steps = int(val["t"].max()) + 1
        print(write_report(cfg, stem, head, [scored], skipped, val, steps, args.boot, **units))
    if skipped:
        print("Left out: " + "; ".join(skipped))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
