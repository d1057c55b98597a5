"""Does Kim's LIDAR DDPG critic rank manoeuvres as the simulator's exact costs do? (family kim)

    python -m experiments.kim_critic_vs_exact experiment=NAME scale=quick [--draw 77] [--trials 200] [--boot 2000]

Straight-line braking drives the scenarios of a validation draw of family kim (``--trials`` per scenario kind, the
evaluation's bank); at each of its decision steps in the first ``agent.kim_chooser.decide_s`` the simulator gives
the exact cost (``kim_unaware``: the summed ISS of the crashes still to come, 0 when nothing is hit) of starting each
of the LIDAR chooser's candidate manoeuvres there (``worldmodel/families/kim/chooser.py``, its labelling, on this
draw). Every trained goal-unaware LIDAR DDPG of the experiment (``agent=ddpg_kim`` and its variants) then scores
each candidate by its critic: -Q(s, a_k), with s the LIDAR view as a live run feeds it (braking before) and a_k the
candidate's first control as Kim's action (desired speed and steering angle, ``envs.kim.kim_action_for`` at the
ego's speed). Q values taking a_k once and then following the actor, not holding the manoeuvre.

The tables and columns are ``experiments/critic_vs_exact.py``'s (Spearman and pairwise order with bootstrap
intervals over scenarios, against a uniformly random choice), with the cost in ISS: "pick - braking" is in ISS
units, and a state "matters" where some candidate is cheaper than braking by more than ``MATTERS_ISS``. Sealed
draws are refused. Writes ``runs/NAME/critic_vs_exact/kim_critic_vs_exact_draw<seed>.md`` and ``.csv``; the labels
are kept beside them (``kim_labels_draw<seed>_trials<N>.npz``) and read again by a later run. A counterfactual-cost
agent (``agent=counterfactual_kim``) is scored by its cost critic on the candidates its shifts drive exactly (braking
and the lane changes), in ``kim_critic_vs_exact_draw<seed>_shifts.md``.
"""

from __future__ import annotations

import argparse
import logging
from types import SimpleNamespace

import numpy as np
import torch

from envs.chooser import decide_steps_for
from envs.kim import kim_action_for
from experiments.critic_vs_exact import Scored, first_action_note, matters, write_report
from worldmodel import artifacts, loading
from worldmodel.banks import sealed_seed_problem, validation_draw
from worldmodel.common import atomic_output
from worldmodel.config import compose, validate
from worldmodel.families.kim import chooser as kim_chooser
from worldmodel.families.kim.evaluation import bank
from worldmodel.families.kim.observe import GOAL_REWARDS, LidarObserver

log = logging.getLogger("kim_critic_vs_exact")
MATTERS_ISS = 0.1  # ISS: a state where some candidate beats braking by more than this is one where choosing matters


def labels(cfg, draw: int, trials: int) -> dict:
    """Braking's decision states on the draw, every candidate costed (``kim_chooser.label_episodes``), as the
    tables read them (``costs``, ``episode``, ``t``); made once and kept in the output folder."""
    typed = validate(cfg)
    path = artifacts.runs_root(cfg) / "critic_vs_exact" / f"kim_labels_draw{draw}_trials{trials}.npz"
    if path.exists():
        data = dict(np.load(path))
    else:
        k = typed.evaluate.kim
        specs = bank(SimpleNamespace(seed=draw, trials=trials, impact_offset=k.impact_offset, impact_offset_spread=0.0))
        steps = decide_steps_for(typed.agent.kim_chooser.decide_s, typed.env.step_s)
        data = kim_chooser.label_episodes(cfg, specs, steps)
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_output(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **data)
    return {**data, "costs": data["cost"], "t": data["step"]}


def critic_scores(state: dict, agent_seed: int, view: np.ndarray, speed: np.ndarray, candidates) -> np.ndarray:
    """-Q(s, a_k) of a LIDAR DDPG checkpoint for every state (rows) and candidate's first control (columns), as
    Kim's action at each state's speed."""
    from worldmodel.models.ddpg import DDPGConfig
    from worldmodel.models.td3 import make_agent

    agent = make_agent(int(state["obs_dim"]), 2, DDPGConfig(**state["ddpg_config"]), agent_seed, device="cpu")
    agent.load_state_dict(state["agent"])
    critic = agent.critic.eval()
    first = [m.action(0) for m in candidates]
    a = np.stack([[kim_action_for(c, float(v)) for c in first] for v in speed]).astype(np.float32)
    s, k = a.shape[:2]
    with torch.inference_mode():
        q = critic(torch.from_numpy(np.repeat(view, k, axis=0)), torch.from_numpy(a.reshape(-1, 2)))
    return -q.reshape(s, k).numpy().astype(np.float64)


def shift_columns(candidates, state: dict) -> list[int]:
    """The candidates (braking first) that a counterfactual actor's shift drives exactly as the chooser does
    (``critic_vs_exact.shift_inputs``): its critic is scored on those columns only."""
    from experiments.critic_vs_exact import shift_inputs

    keep = []
    for j, m in enumerate(candidates):
        try:
            shift_inputs([m], state["hold_s"], float(state["step_s"]))
        except ValueError:
            continue
        keep.append(j)
    return keep


def cost_critic_scores(state: dict, view: np.ndarray, step: np.ndarray, candidates) -> np.ndarray:
    """The counterfactual-cost critic's predicted cost (members' mean) of every candidate, at each state's own
    decision index (the labels' step: decisions are one step apart, as the preset's)."""
    from experiments.critic_vs_exact import cost_critic, shift_inputs
    from worldmodel.models.counterfactual import features

    u = shift_inputs(candidates, state["hold_s"], float(state["step_s"]))
    x = features(view, np.minimum(step, int(state["decisions"]) - 1), int(state["decisions"]))
    critic = cost_critic(state)
    with torch.inference_mode():
        xt = torch.from_numpy(np.repeat(x, len(u), axis=0))
        ut = torch.from_numpy(np.tile(u, (len(x), 1)))
        return critic(xt, ut).mean(0).reshape(len(x), len(u)).numpy().astype(np.float64)


def score_cost_critics(cfg, val: dict, candidates) -> tuple[list[Scored], list[int]]:
    """Every counterfactual-cost LIDAR agent (agent=counterfactual_kim), on the columns its shifts drive."""
    scored, columns = [], []
    for agent in artifacts.trained_agents(cfg, "kim"):
        state = loading.load_agent_state(cfg, agent, "last")
        if state.get("learner") != "counterfactual" or state.get("obs") != "lidar":
            continue
        if int(state["interval"]) != 1 or int(state["obs_dim"]) != val["view"].shape[1]:
            continue  # decisions not one step apart, or another view: the labels' states are not its own
        columns = shift_columns(candidates, state)
        moves = [candidates[j] for j in columns]
        scores = cost_critic_scores(state, val["view"], val["step"], moves)
        scored.append(Scored(agent.key, "cost critic", scores, np.arange(len(val["view"]))))
    return scored, columns


def score_agents(cfg, val: dict, candidates) -> tuple[list[Scored], list[str]]:
    """Every trained kim agent with a DDPG critic that reads the view the labels hold; a line for each left out."""
    scored, skipped = [], []
    for agent in artifacts.trained_agents(cfg, "kim"):
        state = loading.load_agent_state(cfg, agent, "last")
        if state.get("learner") == "counterfactual":
            skipped.append(f"{agent.key}: a cost critic over shifts, scored in the shifts' table")
            continue
        if state.get("obs") != "lidar" or "critic" not in state.get("agent", {}):
            skipped.append(
                f"{agent.key}: no LIDAR DDPG critic ({state.get('learner', 'ddpg')}, obs={state.get('obs')})"
            )
            continue
        trained = state["ddpg_config"]
        see = LidarObserver(
            agent.reward in GOAL_REWARDS,
            int(trained["lidar_scans"]),
            int(trained["lidar_rays"]),
            bool(state.get("lidar_speed", False)),
        )
        if see.goal or see.speed or see.dim != val["view"].shape[1]:
            skipped.append(
                f"{agent.key}: it reads {see.dim} inputs (goal or speed), the labels hold the goal-unaware view"
            )
            continue
        rows = np.arange(len(val["view"]))
        scored.append(
            Scored(agent.key, "DDPG -Q", critic_scores(state, agent.seed, val["view"], val["speed"], candidates), rows)
        )
    return scored, skipped


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. experiment=quick scale=quick")
    parser.add_argument(
        "--draw", type=validation_draw, default=None, help="the validation draw (default: the config's)"
    )
    parser.add_argument("--trials", type=int, default=None, help="trials per scenario kind (default: the evaluation's)")
    parser.add_argument("--boot", type=int, default=2000, help="bootstrap resamples of the scenarios")
    args = parser.parse_intermixed_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(1)
    cfg = compose("train_agent", [*args.overrides, "agent=kim_chooser"])
    draw = cfg.evaluate.kim.seed if args.draw is None else args.draw
    why = sealed_seed_problem(draw)
    if why:
        parser.error(why.split(";")[0] + ": choose a validation draw (worldmodel/banks.py)")
    trials = cfg.evaluate.kim.trials if args.trials is None else args.trials
    candidates = kim_chooser.candidates(cfg.env.step_s)
    steps = decide_steps_for(cfg.agent.kim_chooser.decide_s, cfg.env.step_s)
    val = labels(cfg, draw, trials)
    scored, skipped = score_agents(cfg, val, candidates)
    n_matter = int(matters(val["costs"], MATTERS_ISS).sum())
    lines = [
        f"Experiment {cfg.experiment}, family kim, validation draw {draw}: {len(np.unique(val['episode']))} "
        f"scenarios, {len(val['costs'])} labelled decision states of braking (t = 0-{steps - 1}), {n_matter} of them "
        f"where some candidate beats braking by more than {MATTERS_ISS:g} ISS.",
        "",
        f"{len(candidates)} candidates: the LIDAR chooser's (braking first). {first_action_note(candidates)}",
        "",
        "Scores: DDPG -Q(s, a_k) for each candidate's first control as Kim's action. Costs and 'pick - braking': ISS "
        "(kim_unaware). Intervals: bootstrap 95 % over scenarios.",
        "",
    ]
    units = {"matters_by": MATTERS_ISS, "points": 1.0, "unit": "ISS", "margin_unit": " ISS"}
    text = write_report(cfg, f"kim_critic_vs_exact_draw{draw}", lines, scored, skipped, val, steps, args.boot, **units)
    print(text)
    shifts, columns = score_cost_critics(cfg, val, candidates)
    if shifts:  # the same states, on the candidates a shift drives exactly
        sub = {**val, "costs": val["costs"][:, columns]}
        head = [
            f"Experiment {cfg.experiment}, family kim, validation draw {draw}: the states above, on the {len(columns)} "
            "candidates that a counterfactual actor's shift drives exactly as the chooser does (braking and the "
            f"braking lane changes), {int(matters(sub['costs'], MATTERS_ISS).sum())} states where one beats braking "
            f"by more than {MATTERS_ISS:g} ISS. Scores: the cost critic's predicted ISS (members' mean), at the "
            "state's decision.",
            "",
        ]
        stem = f"kim_critic_vs_exact_draw{draw}_shifts"
        print(write_report(cfg, stem, head, shifts, [], sub, steps, args.boot, **units))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
