"""Kim et al.'s evaluation on family ``kim`` (``evaluate``): the seeded trial bank, every policy through it
(``run_policy``), and what the family runs on the Euro NCAP bank (``ncap_policies``)."""

from __future__ import annotations

import logging

import numpy as np

from envs.kim import CAR_LENGTH, SCENARIOS, Aeb3m, KimSpec
from envs.kim import sample as sample_kim
from envs.policies import StraightLineBraking
from envs.rewards import crash_iss
from envs.streams import KIM_BANK_CROSSING

from ... import artifacts
from ..common import Driven, evaluation, world_model_step_s
from .observe import FAMILY, GOAL_REWARDS, PRESET, family_env
from .report import CEILING, FLOOR, figure, summarise, tables
from .trainer import load_policy

log = logging.getLogger(__name__)


def scripted(cfg) -> list:
    """``evaluate.kim.policies``, in their order: braking, AEB-3m and the planner (minimising the ISS cost)."""
    from envs.planner import PrivilegedPlanner

    from ...config import oracle_settings

    def oracle():
        settings = {**oracle_settings(cfg), "step_s": 0.1, "reward": "kim_unaware"}
        return PrivilegedPlanner.from_settings(**settings)

    make = {"braking": StraightLineBraking, "aeb3m": Aeb3m, "oracle": oracle}
    return [make[name]() for name in cfg.evaluate.kim.policies]


def bank(c) -> list[KimSpec]:
    """``c.trials`` seeded trials per scenario; scenario k's first ``c.paper_trials`` make the paper-sized table. Every
    trial's runner crosses the ego at ``c.impact_offset`` (0 by default, as in training), or uniformly within
    ``c.impact_offset_spread`` of it. ``c``: the typed ``evaluate.kim`` or anything with its int ``seed`` and
    ``trials`` and float offsets."""
    out, half = [], CAR_LENGTH / 2
    for k, scenario in enumerate(SCENARIOS):
        rng = np.random.default_rng([c.seed, k])
        crossing = np.random.default_rng([c.seed, k, KIM_BANK_CROSSING])  # the other fields stay the same
        for _ in range(c.trials):
            spec = sample_kim(rng)
            offset = c.impact_offset
            if c.impact_offset_spread > 0:
                low, high = max(-half, offset - c.impact_offset_spread), min(half, offset + c.impact_offset_spread)
                offset = float(crossing.uniform(low, high))
            out.append(KimSpec(**{**spec.to_dict(), "scenario": scenario, "impact_offset": offset}))
    return out


COLUMNS = [
    "policy",
    "policy_seed",
    "trial",
    "scenario",
    "ego_speed",
    "neutral",
    "end",
    "avoided",
    "crashes",
    "first_crash",
    "iss_kmh",
    "iss_ms",
    "hit_runner",
    "rear_ended",
]


def run_policy(env, policy, specs, policy_seed: int = 0) -> list[dict]:
    from tqdm import tqdm

    from envs.rollout import rollout

    rows = []
    per = {s: 0 for s in SCENARIOS}
    for spec in tqdm(specs, desc=policy.name, unit="trial"):
        o = rollout(env, policy, spec).outcome
        hits = list(env.collisions)
        rows.append(
            {
                "policy": policy.name,
                "policy_seed": policy_seed,
                "trial": per[spec.scenario],
                "scenario": spec.scenario,
                "ego_speed": spec.ego_speed,
                "neutral": int(spec.neutral),
                "end": o["end"],
                "avoided": int(not hits),
                "crashes": len(hits),
                "first_crash": hits[0]["class"] if hits else "",
                "iss_kmh": crash_iss(hits, "kmh"),
                "iss_ms": crash_iss(hits, "ms"),
                "hit_runner": int(any(h["hazard"] for h in hits)),
                "rear_ended": int(any(h.get("ego_side") == "rear" for h in hits)),
            }
        )
        per[spec.scenario] += 1
    return rows


def ncap_policies(cfg) -> list[tuple]:
    """AEB-3m and every goal-unaware LIDAR DDPG on the NCAP bank. A camera agent of the family (agent=ddpg_wm_kim)
    acts at the world model's 1/15 s steps, not at this group's 0.1 s, and is left out (logged); so is the LIDAR
    chooser (agent=kim_chooser) and the counterfactual-cost DDPG (agent=counterfactual_kim): they decide in their
    first steps, and this group acts from the start of each test, so they would only show braking from there."""
    from envs.chooser import ManoeuvreChooser
    from envs.counterfactual import ShiftPolicy
    from envs.kim import Aeb3m

    out = [(Aeb3m(), 0, False, True)]
    for agent in artifacts.trained_agents(cfg, family=FAMILY):
        if agent.reward not in GOAL_REWARDS:
            policy, camera = load_policy(cfg, agent)
            if camera:
                log.info("[ncap] %s: a camera agent of family kim; not run in the 0.1 s kim group", agent.key)
                continue
            if isinstance(policy, (ManoeuvreChooser, ShiftPolicy)):
                log.info("[ncap] %s: a takeover policy, not run from the start of the tests", agent.key)
                continue
            out.append((policy, agent.seed, False, True))
    return out


def draw_suffix(c) -> str:
    """What sets this bank apart from the middle of the flank, for its directory's name (after the bank's own,
    ``artifacts.eval_dir``), so that another placement (``_at+2.25``, ``_spread2.25``) never overwrites it."""
    suffix = ""
    if c.impact_offset:
        suffix += f"_at{c.impact_offset:+g}"
    if c.impact_offset_spread:
        suffix += f"_spread{c.impact_offset_spread:g}"
    return suffix


def evaluate(cfg) -> dict:
    """``evaluate.family=kim``: AEB-3m, braking, the planner, every LIDAR and world-model agent of the family and
    (``evaluate.kim.world_model_agents``) the paper's street-trained agents, on the same seeded trials."""
    return evaluation(cfg, FAMILY, COLUMNS, drive, report, PRESET, folder=draw_suffix)


def drive(cfg, c) -> Driven:
    """The scripted policies and the LIDAR agents at Kim's 0.1 s steps, then the camera agents at their world
    model's."""
    from ...config import validate
    from ...policies import porav_policies

    typed = validate(cfg)
    specs = bank(c)
    agents = artifacts.trained_agents(cfg, family="kim")
    loaded = [(a, *load_policy(cfg, a)) for a in agents]  # fail fast, before any trial runs
    lidar = [(p, a.seed) for a, p, camera in loaded if not camera]
    camera = [(p, a.seed) for a, p, camera in loaded if camera]
    if c.world_model_agents:  # the paper's agents, trained on the street, at the junction as they are
        camera += [(p, s) for p, s, sees, _ in porav_policies(cfg) if sees]
    env = family_env(cfg, "kim_unaware")
    rows = []
    for policy in scripted(cfg):
        rows += run_policy(env, policy, specs)
    for policy, seed in lidar:
        rows += run_policy(env, policy, specs, seed)
    env.close()
    if camera:  # world-model agents act at the step length their world model was trained with
        env = family_env(cfg, "kim_unaware", camera=True, step_s=world_model_step_s(typed))
        for policy, seed in camera:
            rows += run_policy(env, policy, specs, seed)
        env.close()
    return Driven(rows, agents, len(specs), len(c.policies) + len(lidar) + len(camera))


def report(cfg, c, done: Driven, out) -> tuple[dict, dict]:
    """Table 2's layout, the shares of the achievable avoidance and the figure; each policy's headline."""
    from ...training import tensorboard

    summary = summarise(done.rows, c.paper_trials)
    summary["render"] = {"trials": c.trials, "paper_trials": c.paper_trials}  # what tables() is given
    (out / "tables.md").write_text(tables(summary, c.trials, c.paper_trials))
    figure(summary, out / "avoidance.png")
    writer = tensorboard(out)
    for policy, s in summary["policies"].items():
        writer.add_scalar(f"kim/{policy}/avoidance", s["all"]["overall"]["avoidance"], 0)
    writer.close()
    headline = {p: f"avoidance {s['all']['overall']['avoidance']:.1f} %" for p, s in summary["policies"].items()}
    for p, share in summary["shares"].items():
        if p not in (FLOOR, CEILING) and share["share"] is not None:
            headline[p] += f", share {share['share']:.1f} %"
    return summary, headline
