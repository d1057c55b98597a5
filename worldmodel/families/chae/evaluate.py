"""``evaluate.family=chae``: the seeded bank of trials every policy drives, one policy's rows, the evaluation that
writes ``runs/NAME/eval_chae/``, and what runs on the Euro NCAP bank."""

from __future__ import annotations

import logging

import numpy as np

from envs.chae import V_INIT_RANGE, V_PED_RANGE, ChaeSpec, LatestSafeBraking
from envs.streams import CHAE_BANK_SCENARIO_2

from ... import artifacts
from ..common import Driven, evaluation
from .observe import FAMILY, PRESET, family_env
from .policies import SCRIPTED, TTCBraking, ensembles, load_policy
from .report import figures, learning_curves, summarise, tables

log = logging.getLogger(__name__)


def bank(c) -> list[tuple[int, ChaeSpec]]:
    """(scenario, spec): Scenario 1 at every TTC of ``c.ttcs`` and Scenario 2, ``c.trials`` each, seeded (``c``: a
    typed section such as ``evaluate.chae`` or ``agent.chae.select``, or anything with an int ``seed`` and ``trials``
    and float ``ttcs``)."""
    out = []
    for ttc in c.ttcs:
        rng = np.random.default_rng([c.seed, round(ttc * 100)])
        for i in range(c.trials):
            spec = ChaeSpec(
                seed=i,
                ttc=ttc,
                v_init=float(rng.uniform(*V_INIT_RANGE)),
                v_ped=float(rng.uniform(*V_PED_RANGE)),
                far_side=bool(rng.random() < 0.5),
            )
            out.append((1, spec))
    rng = np.random.default_rng([c.seed, CHAE_BANK_SCENARIO_2])
    for i in range(c.trials):
        spec = ChaeSpec(
            seed=i,
            ttc=float(rng.uniform(1.5, 4.0)),
            v_init=float(rng.uniform(*V_INIT_RANGE)),
            v_ped=float(rng.uniform(*V_PED_RANGE)),
            far_side=bool(rng.random() < 0.5),
            crosses=False,
        )
        out.append((2, spec))
    return out


COLUMNS = (
    "policy",
    "policy_seed",
    "scenario",
    "ttc",
    "v_init",
    "v_ped",
    "far_side",
    "end",
    "bump",
    "contact",
    "impact_speed",
    "pedestrian_injury",
    "stop_gap",
)


def run_policy(env, policy, entries, policy_seed: int = 0, leave: bool = True) -> list[dict]:
    from tqdm import tqdm

    from envs.rollout import rollout

    rows = []
    for scenario, spec in tqdm(entries, desc=policy.name, unit="trial", leave=leave):
        o = rollout(env, policy, spec).outcome
        rows.append(
            {
                "policy": policy.name,
                "policy_seed": policy_seed,
                "scenario": scenario,
                "ttc": spec.ttc,
                "v_init": spec.v_init,
                "v_ped": spec.v_ped,
                "far_side": int(spec.far_side),
                "end": o["end"],
                "bump": o["bumped"],
                "contact": int(o["pedestrian_collision"]),
                "impact_speed": o["speed_at_collision"] if o["pedestrian_collision"] else float("nan"),
                "pedestrian_injury": o["pedestrian_injury"],
                "stop_gap": o["gap_to_pedestrian"] if o["end"] == "stop" else float("nan"),
            }
        )
    return rows


def evaluate(cfg) -> dict:
    """``evaluate.family=chae``: every scripted policy and dqn agent on the same seeded trials."""
    return evaluation(cfg, FAMILY, COLUMNS, drive, report, PRESET)


def drive(cfg, c) -> Driven:
    """Every scripted policy of ``c.policies`` (no camera), then every dqn agent and ensemble, on the same trials."""
    entries = bank(c)
    agents, learned = driven(cfg, c)  # fail fast, before any trial runs
    rows = []
    plain = family_env(cfg, camera=False, end_on_bump=False)
    for name in c.policies:
        rows += run_policy(plain, SCRIPTED[name](), entries)
    plain.close()
    for policy in learned:
        env = family_env(cfg, camera=policy.see.camera, end_on_bump=False)
        rows += run_policy(env, policy, entries, policy.policy_seed)
        env.close()
    return Driven(rows, agents, len(entries), len(c.policies) + len(learned))


def report(cfg, c, done: Driven, out) -> tuple[dict, dict]:
    """Table I's layout and the bars, the stopping distances and learning curves; each run's headline."""
    from ...training import tensorboard

    summary = summarise(done.rows, c.ttcs)
    summary["render"] = {"trials": c.trials, "ttcs": c.ttcs}  # what tables() is given
    (out / "tables.md").write_text(tables(summary, c.trials))
    figures(done.rows, summary, out)
    learning_curves(cfg, done.agents, out / "learning_curves.png")
    writer = tensorboard(out)
    for policy, s in summary["policies"].items():
        for ttc, rate in s["bump_rate"].items():
            writer.add_scalar(f"chae/{policy}/bump_rate", rate, int(round(float(ttc) * 10)))
    writer.close()
    headline = {
        f"{r['policy']}/seed{r['seed']}": f"max bump {r['max_bump']:.2f} % (TTC {r['at_ttc']:g} s), needless stops "
        + ("n/a" if r["stops"] is None else f"{r['stops']:.2f} %")
        for r in summary["runs"]
    }
    return summary, headline


def driven(cfg, c) -> tuple[list, list]:
    """(the trained dqn agents, the policies that drive): each agent alone and, with ``c.ensemble``, their mean-Q
    ensembles, or the ensembles only when ``c.singles`` is false (``c``: the typed ``evaluate.chae``)."""
    agents = artifacts.trained_agents(cfg, family=FAMILY)
    learned = [load_policy(cfg, a) for a in agents]
    if c.ensemble:
        grouped = ensembles(agents, learned, c.ensemble)
        learned = learned + grouped if c.singles else grouped
    return agents, learned


def ncap_policies(cfg) -> list[tuple]:
    """TTC braking, latest-safe braking and the dqn agents as the family's evaluation drives them (alone, in
    ensembles, or both: ``evaluate.chae.ensemble`` and ``singles``) on the NCAP bank: pedestrian tests only, but the
    camera variant, which sees cars too."""
    from ...config import validate

    out = [(TTCBraking(), 0, False, False), (LatestSafeBraking(), 0, False, False)]
    _, learned = driven(cfg, validate(cfg).evaluate.chae)
    return out + [(p, p.policy_seed, p.see.camera, p.see.camera) for p in learned]
