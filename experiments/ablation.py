"""The agent ablation: one agent variant per lever, added in turn, trained and judged on the validation bank.

    python -m experiments.ablation experiment=quick [seed=0] [--rows ddpg,speed,...] [--planners brake1,right,...]

Each row is an agent preset (``conf/agent/<row>.yaml`` when one exists, else the overrides in ``ROWS``) trained
with reward R2 as ``runs/NAME/agent_r2_<row>/seed<S>/`` and evaluated on the validation bank
(``evaluate.bank=validation``), never the test bank. Straight-line braking, the planner and the planner variants
in ``PLANNERS`` (the perception ceiling, one-sided teachers) are evaluated once and cached, as is every agent's
rows (keyed by its actor's hash), so adding a row costs one training.

Writes ``runs/NAME/ablation/ablation.md`` (the table: whole-bank share of the achievable improvement, collision
rates by kind, lane departures, injuries) and ``results.csv`` (every row), then prints the table.
"""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path

from worldmodel import artifacts, policies, train_agent
from worldmodel.common import resolve_workers
from worldmodel.config import compose
from worldmodel.families.porav import evaluation as porav_eval
from worldmodel.report import _mean, overall_achievable_share, paired_bootstrap, read_results_csv, write_results_csv

log = logging.getLogger("ablation")

# name -> (the row it extends, what it adds, its own overrides). Names are agent variants.
LEARNER = [
    "agent.ddpg.twin_critics=true",
    "agent.ddpg.policy_delay=2",
    "agent.ddpg.target_noise=0.2",
    "agent.ddpg.n_step=3",
    "agent.ddpg.critic_action_layer=1",
]
CLONE = ["demos.episodes=500", "agent.bc_pretrain_steps=6000"]
ROWS: dict[str, tuple[str | None, str, list[str]]] = {
    "ddpg": (None, "the paper's agent: [z, zhat], the identity action map, DDPG", ["agent.use_speed=false"]),
    "speed": ("ddpg", "+ speed in the observation", ["agent.use_speed=true"]),
    "anchor": (
        "speed",
        "+ braking anchor (untrained actor = braking)",
        ["agent.anchor=brake", "agent.ddpg.actor_final_bound=0"],
    ),
    "grip": ("anchor", "+ grip-scaled steering and noise", ["agent.steer=grip"]),
    "td": ("grip", "+ TD3 (twin critics, smoothing, delay), 3-step returns, action at 2nd critic layer", LEARNER),
    "focus": ("td", "+ focus training mix (half the episodes)", ["agent.focus_share=0.5"]),
    "bc": ("focus", "planner demonstrations: behaviour cloning only, no RL", [*CLONE, "agent.total_steps=0"]),
    "dag": (
        "bc",
        "+ 2 DAgger rounds of 100 episodes (the planner labels the student's states)",
        ["agent.dagger_rounds=2", "agent.dagger_episodes=100"],
    ),
    "dagreg": (
        "dag",
        "+ cloning regularised: weight decay 0.01, stopped early on held-out demonstrations",
        ["agent.ddpg.bc_weight_decay=0.01"],
    ),
    "view": (
        "dag",
        "+ the raw frame's hazard profiles (where pedestrians and vehicles are, this frame and the last)",
        ["agent.frame_view=true"],
    ),
    "right": (
        "dag",
        "+ a one-sided teacher: the planner steering right only (demos.teacher_sides=[1.0])",
        ["demos.teacher_sides=[1.0]"],
    ),
    "rightview": ("right", "+ the raw frame's hazard profiles", ["agent.frame_view=true"]),
    "chooser": (
        None,
        "the chooser: brakes, then within 0.2 s switches once to the 0.3 s lane change whose cost its scorer predicts "
        "lowest from [z, zhat, speed, frame view] (costs labelled by the simulator on braking's states; a perception "
        "head learns the privileged hazard state beside)",
        ["agent=chooser"],
    ),
    "chooserwm": (
        "chooser",
        "the chooser on the world model alone: [z, zhat, speed], no frame view",
        ["agent.frame_view=false"],
    ),
    "fd": (
        "focus",
        "+ cloning, then DDPG from demonstrations (25 % demo batches, Q-filtered cloning)",
        [*CLONE, "agent.demo_share=0.25", "agent.ddpg.bc_weight=1.0"],
    ),
}


# planner variants evaluated beside the rows: name -> (what it shows, overrides); policy ``oracle_<name>``
PLANNERS: dict[str, tuple[str, list[str]]] = {
    **{
        f"brake{k}": (
            f"the planner after braking straight for {k} frame(s): perception ceiling",
            [f"evaluate.oracle.brake_first={k}"],
        )
        for k in (1, 2, 3)
    },
    "right": (
        "the planner steering right only: a teacher without left/right ambiguity",
        ["evaluate.oracle.sides=[1.0]"],
    ),
    "left": ("the planner steering left only", ["evaluate.oracle.sides=[-1.0]"]),
    "chooser": ("the chooser's rule on exact costs (agent.chooser's candidates): its ceiling", []),
}


def row_overrides(name: str) -> list[str]:
    """The overrides of row ``name``: those of the rows it extends, then its own."""
    if name not in ROWS:
        raise SystemExit(f"unknown ablation row {name!r}: use {', '.join(ROWS)}")
    parent, _, own = ROWS[name]
    inherited = [o for o in row_overrides(parent) if not o.startswith("agent.variant=")] if parent else []
    return [*inherited, *own, f"agent.variant={name}"]


def cached_rows(path: Path, sha: str | None, make) -> list[dict]:
    if path.exists():
        rows = read_results_csv(path)
        if sha is None or all(r.get("actor_sha") == artifacts.short(sha) for r in rows):
            return rows
    rows = make()
    write_results_csv(rows, path)
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. experiment=quick seed=0")
    parser.add_argument("--rows", default=",".join(ROWS), help="comma-separated rows, in order")
    parser.add_argument(
        "--planners", default="brake1,brake2", help=f"comma-separated planner variants: {', '.join(PLANNERS)}"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    base = [*args.overrides, "reward=r2", "evaluate.bank=validation"]
    cfg = compose("evaluate", base)
    out = artifacts.runs_root(cfg) / "ablation"
    out.mkdir(parents=True, exist_ok=True)
    entries = porav_eval.bank(cfg)
    workers = resolve_workers(cfg.evaluate.num_workers)

    rows = []
    for name in ("braking", "oracle"):
        make = lambda n=name: porav_eval.evaluate_policy(cfg, n, entries, workers)  # noqa: E731
        rows += cached_rows(out / f"rows_{name}.csv", None, make)
    planners = [p for p in args.planners.split(",") if p]
    for p in planners:
        if p not in PLANNERS:
            raise SystemExit(f"unknown planner row {p!r}: use {', '.join(PLANNERS)}")
        variant = compose("evaluate", [*base, *PLANNERS[p][1]])

        def make(c=variant, p=p):
            source = policies.EXACT_CHOOSER if p == "chooser" else "oracle"
            return [r | {"policy": f"oracle_{p}"} for r in porav_eval.evaluate_policy(c, source, entries, workers)]

        rows += cached_rows(out / f"rows_oracle_{p}.csv", None, make)
    table = []
    for name in [r for r in args.rows.split(",") if r]:
        agent_cfg = compose("train_agent", [*base, *row_overrides(name)])
        agent = artifacts.AgentId.of(agent_cfg)
        if not (agent.dir(agent_cfg) / "metrics.json").exists():
            log.info("[ablation] training %s", agent.key)
            train_agent.run(agent_cfg)
        eval_cfg = compose("evaluate", [*base, *row_overrides(name)])
        sha = artifacts.actor_id(eval_cfg, agent)
        make = lambda a=agent, c=eval_cfg: porav_eval.evaluate_policy(c, a.key, entries, workers)  # noqa: E731
        rows += cached_rows(out / f"rows_{name}_seed{agent.seed}.csv", sha, make)
        table.append((name, agent.policy))
    # every seed evaluated so far for the rows asked for: the table pools them
    for name, policy in table:
        for path in sorted(out.glob(f"rows_{name}_seed*.csv")):
            if not any(r["policy"] == policy and path.stem.endswith(f"seed{r['policy_seed']}") for r in rows):
                rows += read_results_csv(path)
    write_results_csv(rows, out / "results.csv")
    text = ablation_markdown(rows, table, cfg, planners)
    (out / "ablation.md").write_text(text)
    print(text)
    return 0


def ablation_markdown(rows: list[dict], table: list[tuple[str, str]], cfg, planners=()) -> str:
    head = [
        "row",
        "what it adds",
        "share of achievable %",
        "share 95 % CI",
        "vs braking, pts (95 % CI)",
        "total risk %",
        "pedestrian coll. %",
        "vehicle coll. %",
        "static coll. %",
        "lane departure %",
        "pedestrian injury",
        "occupant injury",
    ]
    lines = [
        f"Validation bank (seed {cfg.evaluate.validation_seed}, {len(porav_eval.bank(cfg))} scenarios), reward R2, "
        "Training seeds as listed, pooled. Rates are % of all scenarios; injuries are mean P(severe) per scenario.",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * 2 + "---:|" * (len(head) - 2),
    ]

    def line(label, what, policy):
        prow = [r for r in rows if r["policy"] == policy]
        share = (
            overall_achievable_share(rows, policy)
            if policy not in ("braking", "oracle")
            else (0.0 if policy == "braking" else 100.0)
        )
        total = 100 * _mean(prow, "total_injury")
        cells = [label, what, "n/a" if math.isnan(share) else f"{share:.0f}"]
        if policy in ("braking", "oracle") or policy.startswith("oracle_"):
            cells += ["", ""]
        else:  # paired bootstrap over scenarios, the policy's seeds averaged per scenario
            b = paired_bootstrap(rows, policy)
            lo, hi = b["share_ci95"]
            dlo, dhi = b["difference_ci95"]
            interval = "n/a" if math.isnan(lo) else f"[{lo:.0f}, {hi:.0f}]"
            cells += [interval, f"{b['difference_pts']:+.2f} [{dlo:+.2f}, {dhi:+.2f}]"]
        cells.append(f"{total:.2f}")
        cells += [
            f"{100 * _mean(prow, c):.1f}"
            for c in ("pedestrian_collision", "vehicle_collision", "static_collision", "lane_departure")
        ]
        cells += [f"{_mean(prow, c):.4f}" for c in ("pedestrian_injury", "occupant_injury")]
        lines.append("| " + " | ".join(cells) + " |")

    line("braking", "straight-line emergency braking (the floor)", "braking")
    for name, policy in table:
        seeds = sorted({int(r["policy_seed"]) for r in rows if r["policy"] == policy})
        line(f"{name} (seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))})", ROWS[name][1], policy)
    for p in planners:
        line(f"planner, {p}", PLANNERS[p][0], f"oracle_{p}")
    line("planner", "privileged planner (the ceiling)", "oracle")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
