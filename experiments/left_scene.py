"""What leaving the scene hides: the validation episodes that ended ``left_scene``, replayed with the bound far away.

    python -m experiments.left_scene experiment=headline scale=paper --rows docs/results/porav/validation.rows.csv.gz \
        --policies oracle,oracle_brake1,oracle_brake2
    python -m experiments.left_scene experiment=quick scale=quick --policies agent_r1/seed0,agent_r2/seed0

``UrbanCollisionEnv`` ends an episode as ``left_scene``, at no further cost, once the ego is more than
``env.lateral_exit_m`` (25 m) from the street's centre line, beyond every static body: it gets there through a gap
in them (the side street's opening, between buildings), still moving. This script takes the validation bank's scenarios
(the paper family's ``evaluation.bank``) in which each policy left the scene under the configured
bound, read from ``--rows`` (a committed ``*.rows.csv.gz`` or an evaluation's ``results.csv``, whose endings
``experiments.episode_endings`` reads) or, without it, found by running the policy on the whole bank, and runs each
of them three ways:

* ``bound``: the configured bound, as evaluated (checked against the rows' ``steps`` and ``return_r2``);
* ``far, same plans``: the bound at ``--far`` metres, while a policy that plans on the env's ``planning_twin`` (the
  privileged planner) still plans with the configured bound, so it drives the same episode up to the exit and then
  carries on with its plan: what the exit hid of that very episode. For a policy that does not plan on a twin it
  is the same run as the next;
* ``far``: the bound at ``--far`` metres for the env and its planning twin alike: what the policy gets when leaving
  does not end anything.

A policy is built as evaluation builds it (``worldmodel.policies.policy_for``: scripted names like ``oracle`` or
``oracle_brake1``, trained agents' keys like ``agent_r2/seed0``), with the camera on for those that read it, and
driven by ``envs.rollout``. Prints one markdown line per policy: its episodes, their summed R2 cost each way, how
many of the far-bound episodes crossed the configured bound, what they hit after crossing, and their mean final
speed; ``--episodes`` adds one line per episode. The first command takes about 30 s (50 episodes, three ways each);
without ``--rows`` every scenario of the bank is run once more to find the episodes (~2 min for a planner at quick
scale).
"""

from __future__ import annotations

import argparse
import math
from collections import Counter

from experiments.episode_endings import LEFT, ending
from worldmodel.banks import ledger_key
from worldmodel.common import make_env, set_threads
from worldmodel.config import SCRIPTED_POLICIES, compose
from worldmodel.policies import EXACT_CHOOSER, env_overrides, policy_for

WAYS = ("bound", "far, same plans", "far")


def _needs_camera(policy, name: str) -> bool:
    """As ``worldmodel.evaluate``: the scripted policies read the true state, unless one says it needs the frame."""
    return getattr(policy, "needs_camera", name not in (*SCRIPTED_POLICIES, EXACT_CHOOSER))


def _env(cfg, name: str, bound: float, plan_bound: float):
    """(env, policy) for ``name``: a fresh policy (a planner keeps the first twin it is bound to), the env's
    lateral exit at ``bound``, its planning twins' at ``plan_bound``."""
    from envs import UrbanCollisionEnv

    policy, _, _ = policy_for(cfg, name)
    env = make_env(cfg, camera=_needs_camera(policy, name), lateral_exit_m=bound, **env_overrides(policy))
    if plan_bound != bound:

        def twin():
            out = UrbanCollisionEnv.planning_twin(env)
            out.lateral_exit_m = plan_bound
            return out

        env.planning_twin = twin
    return env, policy


def run_episode(env, policy, spec, exit_m: float) -> dict:
    """One episode: its outcome, and what happened once the ego was more than ``exit_m`` m off the centre line (the
    step it first was, the collisions from then on, as ``kind:class``)."""
    from envs.rollout import rollout

    after: dict = {"crossed": None, "hits": []}

    def on_step(obs, action, reward, info):
        if after["crossed"] is None and abs(info["y"]) > exit_m:
            after["crossed"] = info["step"]
        if after["crossed"] is not None:
            after["hits"] += [f"{c['kind']}:{c['class']}" for c in info["collisions"]]

    o = rollout(env, policy, spec, on_step=on_step).outcome
    return {"outcome": o, "cost": -o["return_r2"], **after}


def left_entries(cfg, name: str, entries, rows: list[dict] | None) -> tuple[list, dict]:
    """The bank entries in which ``name`` left the scene, and its rows by scenario id (empty when found by running
    it: those runs are the bound's)."""
    if rows is None:
        env, policy = _env(cfg, name, cfg.env.lateral_exit_m, cfg.env.lateral_exit_m)
        found = [e for e in entries if run_episode(env, policy, e.spec, math.inf)["outcome"]["end"] == "left_scene"]
        env.close()
        return found, {}
    step_s, after = float(cfg.env.step_s), cfg.env.horizon_after_ttc_s
    mine = {r["scenario_id"]: r for r in rows if ledger_key(r) == name}
    if not mine:
        raise SystemExit(f"no rows of {name} in the rows file (it has {sorted({ledger_key(r) for r in rows})})")
    by_id = {e.scenario_id: e for e in entries}
    left = [r for r in mine.values() if ending(r, 0.5, step_s, after) == LEFT]
    for r in left:
        entry = by_id.get(r["scenario_id"])
        if entry is None or entry.spec.seed != r["seed"]:
            raise SystemExit(
                f"{name}'s row for scenario {r['scenario_id']} (seed {r['seed']}) is not in this config's bank: "
                "give the overrides of the experiment and scale the rows were made with"
            )
    return [by_id[r["scenario_id"]] for r in left], mine


def replay(cfg, name: str, entries, rows: list[dict] | None, far: float) -> list[dict]:
    """One record per left-scene episode of ``name``: its scenario, the row it reproduces (or None), and each way's
    episode (``WAYS``)."""
    bound = float(cfg.env.lateral_exit_m)
    chosen, mine = left_entries(cfg, name, entries, rows)
    ways = {"bound": (bound, bound), "far, same plans": (far, bound), "far": (far, far)}
    out = [{"entry": e, "row": mine.get(e.scenario_id)} for e in chosen]
    for way, (exit_m, plan_m) in ways.items():
        env, policy = _env(cfg, name, exit_m, plan_m)
        if way == "far, same plans" and getattr(policy, "bind", None) is None:  # nothing plans on a twin
            env.close()
            continue
        for rec in out:
            rec[way] = run_episode(env, policy, rec["entry"].spec, bound)
        env.close()
    for rec in out:
        rec.setdefault("far, same plans", rec["far"])
    return out


def _reproduced(rec: dict) -> bool:
    """Whether the replay under the configured bound ran the row's steps to the row's R2 return."""
    row, o = rec["row"], rec["bound"]["outcome"]
    return o["steps"] == row["steps"] and math.isclose(o["return_r2"], row["return_r2"], rel_tol=1e-9, abs_tol=1e-12)


def _after(recs: list[dict], way: str) -> tuple[str, str, str]:
    """(crossed the bound, what was hit after crossing, mean final speed of those that crossed) of ``way``."""
    crossed = [r[way] for r in recs if r[way]["crossed"] is not None]
    hits = Counter(h for r in crossed for h in r["hits"])
    speed = sum(r["outcome"]["final_speed"] for r in crossed) / len(crossed) if crossed else math.nan
    return (
        str(len(crossed)),
        ", ".join(f"{k} x{n}" for k, n in sorted(hits.items())) or "none",
        "—" if math.isnan(speed) else f"{speed:.1f}",
    )


def table(results: dict[str, list[dict]]) -> str:
    head = [
        "policy",
        "left-scene episodes",
        "reproduced",
        "R2 cost, bound",
        "R2 cost, far, same plans",
        "R2 cost, far",
        "crossed, same plans",
        "hits after crossing, same plans",
        "final speed after crossing, same plans, m/s",
        "crossed, far",
        "hits after crossing, far",
        "final speed after crossing, far, m/s",
        "endings, far",
    ]
    lines = ["| " + " | ".join(head) + " |", "|---|" + "---:|" * 6 + "---|---:|---:|---|---:|---|"]
    for name, recs in results.items():
        costs = [f"{sum(r[w]['cost'] for r in recs) + 0.0:.4f}" for w in WAYS]  # + 0.0: no "-0.0000"
        ends = Counter(r["far"]["outcome"]["end"] for r in recs)
        checked = [r for r in recs if r["row"] is not None]  # none when found by running: nothing to check against
        reproduced = f"{sum(map(_reproduced, checked))}/{len(checked)}" if checked else "—"
        cells = [name, str(len(recs)), reproduced, *costs]
        cells += [*_after(recs, "far, same plans"), *_after(recs, "far")]
        cells.append(", ".join(f"{k} {n}" for k, n in sorted(ends.items())) or "—")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def episode_lines(results: dict[str, list[dict]]) -> str:
    head = ["policy", "scenario", "hazard", "TTC s", "speed m/s", "steps (row)", "steps"]
    head += [*(f"R2 cost, {w}" for w in WAYS), "end, far", "hits after crossing, far", "final speed, far"]
    lines = ["| " + " | ".join(head) + " |", "|---|---:|---|" + "---:|" * 7 + "---|---|---:|"]
    for name, recs in results.items():
        for r in recs:
            e, row, far = r["entry"], r["row"], r["far"]
            cells = [name, str(e.scenario_id), e.hazard, f"{e.ttc:g}", f"{e.speed:g}"]
            cells += ["—" if row is None else str(row["steps"]), str(r["bound"]["outcome"]["steps"])]
            cells += [f"{r[w]['cost'] + 0.0:.4f}" for w in WAYS]
            cells += [far["outcome"]["end"], ", ".join(far["hits"]) or "none", f"{far['outcome']['final_speed']:.1f}"]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. experiment=quick scale=quick")
    parser.add_argument("--policies", required=True, help="comma-separated: oracle, oracle_brake1, agent_r2/seed0, ...")
    parser.add_argument("--rows", default=None, help="the validation rows that say which episodes left the scene")
    parser.add_argument("--far", type=float, default=1e4, help="m: the far lateral bound")
    parser.add_argument("--episodes", action="store_true", help="also one line per episode")
    args = parser.parse_intermixed_args(argv)  # Hydra overrides may come after the options
    from worldmodel.families.porav.evaluation import bank
    from worldmodel.report import read_results_csv

    set_threads(1)
    cfg = compose("evaluate", args.overrides)
    if cfg.evaluate.bank != "validation":
        parser.error("the left-scene replay runs on a validation bank only")
    entries = bank(cfg)
    rows = read_results_csv(args.rows) if args.rows else None
    results = {name: replay(cfg, name, entries, rows, args.far) for name in args.policies.split(",") if name}
    print(f"### Left-scene episodes, bound {cfg.env.lateral_exit_m:g} m against {args.far:g} m\n")
    print(table(results))
    if args.episodes:
        print()
        print(episode_lines(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
