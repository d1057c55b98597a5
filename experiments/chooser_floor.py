"""The trained choosers under a floor on switching, exactly and offline, on the validation bank.

    python -m experiments.chooser_floor experiment=paper scale=paper [--agent chooser_tele] [--seeds 0,1,2]
        [--floors 0,0.05] [--margins 0.02,0.05] [--penalties 0,0.2] [--ensemble] [--validation-seeds 4711,4712]

``agent.chooser.min_brake_cost`` lets the chooser switch only where its scorer predicts braking to cost more than
the floor. It is a decision-time rule, so the trained scorers (``runs/NAME/agent_r2_chooser/seed<S>/``) are scored
as they are: on the validation bank's labels (``data/NAME/chooser_labels/validation-*/``, made once if missing),
each seed's exact R2 cost per scenario (``worldmodel.chooser.policy_cost``, equal to the simulated episode) under
each floor. Prints, per floor, the mean gain over braking per seed, the static-collision rate (where the labels
record, per candidate, whether it ends in a static object; older labels lack the flags) and the TTC <= 1.0 s cells in
which the seed-averaged chooser costs more than braking (the bar on those cells: no higher than braking's). First,
from the labels alone, the exact-cost chooser under static penalties (``agent.chooser.static_penalty``); with
``--ensemble``, also the seeds' predictions averaged. The test bank is never touched.

A margin other than the one the scorers were trained with is a what-if of the decision rule alone: training keeps
the scorer checkpoint that is best on its held-out labels at the preset's margin, so a chooser trained with another
margin may keep another checkpoint.
"""

from __future__ import annotations

import argparse
import logging
from collections import defaultdict

import numpy as np
import torch

from worldmodel import artifacts, chooser, loading
from worldmodel.artifacts import AgentId
from worldmodel.banks import validation_draw
from worldmodel.config import compose

log = logging.getLogger("chooser_floor")


def predictions(base: list[str], seeds: list[int], val: dict) -> list[np.ndarray]:
    """Each seed's predicted costs on the validation labels, as its live chooser sees them."""
    out = []
    encoder = None
    for seed in seeds:
        cfg = compose("train_agent", [*base, f"seed={seed}"])
        encoder = encoder or loading.load_world_model(cfg)
        state = loading.load_agent_state(cfg, AgentId.of(cfg), "last")
        scorer = chooser.build_policy("floor", encoder, state).scores.scorer
        x = chooser.scorer_inputs(
            encoder, val, int(state["decide_steps"]), bool(state.get("mask_view")), state.get("mask_camera", "wide")
        )
        out.append(scorer.predict(x))
    return out


def pooled_validation(base: list[str], banks: list[int | None], seeds: list[int]):
    """The labels of one or more validation banks (``evaluate.validation_seed`` values; None = the config's), one
    after the other with episode numbers kept apart; each scenario's (speed, TTC) cell; and each bank's
    predictions per trained seed."""
    parts, cells, per_bank, offset = [], [], [], 0
    for bank in banks:
        overrides = [*base] if bank is None else [*base, f"evaluate.validation_seed={bank}"]
        cfg = compose("train_agent", overrides)
        val = chooser.labels(cfg, "validation")
        per_bank.append(predictions(overrides, seeds, val))
        parts.append({**val, "episode": val["episode"] + offset})
        entries = chooser.validation_entries(cfg)
        cells += [(e.speed, e.ttc) for e in entries]
        offset += len(entries)
    keys = [k for k in parts[0] if all(k in p for p in parts)]
    return {k: np.concatenate([p[k] for p in parts]) for k in keys}, cells, per_bank


def exact_penalty_table(costs, static, episode, braking, margins, penalties: str) -> list[str]:
    """The exact-cost chooser deciding on its costs plus ``penalty`` where a candidate hits a static object (what
    ``agent.chooser.static_penalty`` teaches the scorer), scored on the true costs: what the penalty can buy."""
    if static is None or not penalties:
        return []
    lines = [
        "The exact-cost chooser deciding on costs + penalty x (ends in a static object), scored on the true costs:",
        "",
        "| static_penalty | margin | risk - braking, pts | static coll. % |",
        "|---:|---:|---:|---:|",
    ]
    for penalty in [float(p) for p in penalties.split(",")]:
        decided = costs + np.float32(penalty) * static
        for margin in margins:
            cost = chooser.policy_cost(decided, costs, episode, margin)
            hits = chooser.policy_static(decided, static, episode, margin)
            lines.append(
                f"| {penalty:g} | {margin:g} | {100 * (cost.mean() - braking.mean()):+.2f} | {100 * hits.mean():.2f} |"
            )
    return [*lines, ""]


def learned_table(preds, costs, static, episode, braking, cells, margins, floors) -> list[str]:
    """Per (margin, floor): each seed's gain over braking, static-collision rate, and the TTC <= 1.0 s cells in
    which the seed-averaged chooser costs more than braking."""
    lines = [
        "| margin | min_brake_cost | risk - braking, pts, per seed | mean | static coll. %, per seed | "
        "TTC <= 1.0 s cells above braking (chooser / braking, %) |",
        "|---:|---:|---|---:|---|---|",
    ]
    for margin in margins if preds else []:
        for floor in floors:
            window = {"min_brake_cost": floor}
            per_seed = [chooser.policy_cost(p, costs, episode, margin, **window) for p in preds]
            hits = (
                "n/a (labels without static flags)"
                if static is None
                else ", ".join(
                    f"{100 * chooser.policy_static(p, static, episode, margin, **window).mean():.1f}" for p in preds
                )
            )
            mean = np.mean(np.asarray(per_seed, np.float64), axis=0)  # float32 means left ~1e-8 excesses
            by_cell = defaultdict(list)
            for i, cell in enumerate(cells):
                by_cell[cell].append((mean[i], float(braking[i])))
            worse = []
            for (speed, ttc), pairs in sorted(by_cell.items()):
                mine, theirs = (100 * float(np.mean(v)) for v in zip(*pairs))
                if ttc <= 1.0 and mine > theirs + 1e-9:
                    worse.append(f"{speed:g} m/s {ttc:g} s: {mine:.2f} / {theirs:.2f}")
            gains = [100 * float(c.mean() - braking.mean()) for c in per_seed]
            lines.append(
                f"| {margin:g} | {floor:g} | {', '.join(f'{g:+.2f}' for g in gains)} | {np.mean(gains):+.2f} | "
                f"{hits} | {'; '.join(worse) or 'none'} |"
            )
            log.info(lines[-1])
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. experiment=paper scale=paper")
    parser.add_argument("--agent", default="chooser", help="the chooser preset: chooser or chooser_tele")
    parser.add_argument("--seeds", default="0,1,2", help="trained seeds to score; empty: the exact-cost table only")
    parser.add_argument(
        "--penalties",
        default="0,0.05,0.1,0.2,0.5,1",
        help="static penalties (agent.chooser.static_penalty) for the exact-cost chooser's table",
    )
    parser.add_argument("--floors", default="0,0.02,0.03,0.04,0.05,0.07,0.1,0.15")
    parser.add_argument("--margins", default=None, help="comma-separated; default: the chooser preset's")
    parser.add_argument("--ensemble", action="store_true", help="also the seeds' predictions averaged")
    parser.add_argument(
        "--validation-seeds",
        default=None,
        help="comma-separated evaluate.validation_seed values whose banks are pooled (each labelled once); "
        "default: the config's. More banks make the cells rule judge each cell on more scenarios",
    )
    args = parser.parse_intermixed_args(argv)  # Hydra overrides may come after the options
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(1)
    base = [*args.overrides, "reward=r2", f"agent={args.agent}", "agent.chooser.num_workers=1"]
    cfg = compose("train_agent", base)
    margins = [float(m) for m in args.margins.split(",")] if args.margins else [float(cfg.agent.chooser.margin)]
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    try:
        banks = [validation_draw(v) for v in args.validation_seeds.split(",")] if args.validation_seeds else [None]
    except argparse.ArgumentTypeError as err:
        parser.error(f"--validation-seeds: {err}")
    val, cells, per_bank = pooled_validation(base, banks, seeds)
    costs, episode, static = val["costs"], val["episode"], val.get(chooser.STATIC_KEY)
    braking = costs[np.r_[True, episode[1:] != episode[:-1]], 0]
    exact = chooser.policy_cost(costs, costs, episode, 0.0)
    preds = [np.concatenate(p) for p in zip(*per_bank, strict=True)] if seeds else []
    exact_static = "n/a" if static is None else f"{100 * chooser.policy_static(costs, static, episode, 0.0).mean():.1f}"
    lines = [
        f"Validation bank{'s ' + args.validation_seeds if args.validation_seeds else ''}, {len(braking)} "
        f"scenarios, agent={args.agent}: braking {100 * braking.mean():.2f} %, the "
        f"chooser on exact costs {100 * exact.mean():.2f} % (mean R2 total risk; its static collisions "
        f"{exact_static} %).",
        "",
        *exact_penalty_table(costs, static, episode, braking, margins, args.penalties),
        "The trained seeds:",
        "",
    ]
    floors = [float(f) for f in args.floors.split(",")]
    lines += learned_table(preds, costs, static, episode, braking, cells, margins, floors)
    if args.ensemble and len(preds) > 1:
        lines += [
            "",
            "The seeds' scorers averaged into one (what agent.chooser.ensemble would train in one run):",
            "",
            *learned_table([np.mean(preds, axis=0)], costs, static, episode, braking, cells, margins, floors),
        ]
    out = artifacts.runs_root(cfg) / "chooser_floor"
    out.mkdir(parents=True, exist_ok=True)
    text = "\n".join(lines) + "\n"
    (out / f"floor-{args.agent}.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
