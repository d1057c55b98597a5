"""The whole pipeline in order: collect, VAE, LSTM, agents R1 and R2, evaluation; make-like.

    python -m worldmodel.pipeline experiment=NAME scale=smoke|quick|paper

Before each stage the pipeline compares what the stage's outputs were built from (the identities of their
inputs and the hash of their config keys, recorded in ``provenance.json``; docs/design.md §9) with what they would
be built from now:

* up to date and finished: skipped;
* up to date but unfinished (interrupted): continued with ``resume=true``;
* stale (an input or the config changed since): the old outputs are moved to ``runs/NAME/stale/`` and the stage
  runs afresh, and so, through their changed inputs, does every stage downstream of it.

Agents are the presets of ``agents``, each with its rewards, at every seed of ``seeds`` (``seed`` when empty), plus
any other trained seed found on disk, so a seed sweep is rebuilt too when the world model changes. The evaluation
runs once per bank of ``banks`` (worldmodel/banks.py): ``[validation]`` by default; ``test`` is for final numbers
and records itself in the ledger. ``peers=[chae]`` adds a peer system (docs/design.md
§10), by family or by preset (``ddpg_kim_fd``): its agents on its own scenario family at every seed (Chae's: the
members of one ensemble per seed), then that family's evaluation per bank (``runs/NAME/eval_chae/``).
``agents=[]`` leaves the paper's family out: a run of peers alone never touches the Porav test bank.

The collection is the root: its own settings check stops a run whose collection settings differ. Each stage's wall
time and peak memory (this process and its workers, sampled every 0.2 s) are written to ``runs/NAME/pipeline.json``.
"""

from __future__ import annotations

import json
import logging
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from omegaconf import OmegaConf

from . import artifacts, launcher, registry
from .artifacts import AgentId
from .common import StageError, atomic_write_text, writer_lock
from .config import agent_preset, hydra_main, peer_preset, preset_globals, validate

log = logging.getLogger(__name__)


class PeakMemory:
    """Samples the resident memory of this process and its children in a background thread."""

    def __init__(self, interval: float = 0.2):
        import psutil

        self._proc = psutil.Process()
        self.interval, self.peak_mb = interval, 0.0
        self._stop = threading.Event()

    def _sample(self) -> float:
        total = 0
        for p in [self._proc, *self._proc.children(recursive=True)]:
            try:
                total += p.memory_info().rss
            except Exception:  # a worker that just exited
                pass
        return total / 2**20

    def _loop(self):
        while not self._stop.is_set():
            self.peak_mb = max(self.peak_mb, self._sample())
            self._stop.wait(self.interval)

    def __enter__(self):
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        return False


@dataclass
class Step:
    """One stage run of the pipeline: its name in logs and timings, its kind (``artifacts.provenance``), the
    stage's ``run`` and the config changes it runs with."""

    name: str
    kind: str
    run: Callable[[object], dict]
    changes: dict = field(default_factory=dict)
    agent: AgentId | None = None


def peer_seeds(cfg, variant: str) -> list[int]:
    """The seeds a peer's agent trains with: those of ``seeds`` (``seed`` when empty). A family whose agents are
    judged as ensembles of k consecutive seeds (``Family.ensemble_key``: Chae's DQN) trains every member instead:
    ensemble s is seeds s*k..s*k+k-1 and drives under seed s, so ``seeds=[0,1,2]`` gives three ensembles of three
    runs."""
    seeds = list(cfg.seeds) or [cfg.seed]
    family = registry.family(preset_globals(variant).get("env", {}).get("family") or registry.default().name)
    k = OmegaConf.select(cfg, family.ensemble_key) if family.ensemble_key else 0
    if k:
        return sorted({m for s in seeds for m in range(s * k, s * k + k)})
    return sorted(seeds)


def eval_suffix(bank: str) -> str:
    return "" if bank == "validation" else f"_{bank}"


def steps(cfg) -> list[Step]:
    """The stages in order: every later stage only reads what the earlier ones wrote."""
    from . import collect, demonstrate, evaluate, train_agent, train_rnn, train_vae

    seeds = list(cfg.seeds) or [cfg.seed]
    agents = {AgentId(r, s, v) for v in cfg.agents for r in agent_preset(cfg, v).rewards for s in seeds}
    paper = bool(cfg.agents)  # agents=[]: the paper's family is left out, its agents and its evaluations alike
    if paper:
        agents |= set(artifacts.trained_agents(cfg))
    peers = [peer_preset(p) for p in cfg.peers]
    peer_agents = {AgentId(r, s, v) for v in peers for r in agent_preset(cfg, v).rewards for s in peer_seeds(cfg, v)}
    for family in {a.family for a in peer_agents}:
        peer_agents |= set(artifacts.trained_agents(cfg, family))

    def agent_step(a: AgentId) -> Step:
        changes = {**preset_globals(a.variant), "reward": {"name": a.reward}, "seed": a.seed}
        preset = agent_preset(cfg, a.variant)
        if a.obs:  # another observation than its paper's (obs=NAME when it was trained)
            preset = OmegaConf.merge(preset, {"obs": a.obs})
        return Step(
            a.key if a.seed != cfg.seed or a.obs else a.policy,
            "agent",
            train_agent.run,
            {**changes, "agent": preset},
            a,
        )

    agent_steps = [agent_step(a) for a in sorted(agents)]
    peer_steps = []
    family_of = {v: preset_globals(v)["env"]["family"] for v in peers}
    for family in dict.fromkeys(family_of.values()):  # in the order of peers: each family's agents, then its banks
        peer_steps += [agent_step(a) for a in sorted(peer_agents) if a.family == family]
        globals_ = preset_globals(peer_preset(family))  # evaluated as its paper's preset sets the family up
        for bank in cfg.banks:
            changes = {**globals_, "evaluate": {"family": family, "bank": bank}}
            name = registry.family(family).folder + eval_suffix(bank)
            peer_steps.append(Step(name, "eval", evaluate.run, changes))
    paper_eval, banks = registry.default().folder, cfg.banks if paper else []
    needs_demos = any(artifacts.uses_demos(OmegaConf.merge(cfg, s.changes).agent) for s in agent_steps)
    if needs_demos and cfg.demos.episodes < 1:
        users = [s.name for s in agent_steps if artifacts.uses_demos(OmegaConf.merge(cfg, s.changes).agent)]
        raise StageError(f"{', '.join(users)} learn from planner demonstrations: pass demos.episodes=N (e.g. 300)")
    return [
        Step("collect", "collect", collect.run),
        Step("vae", "vae", train_vae.run),
        Step("rnn", "rnn", train_rnn.run),
        *([Step("demos", "demos", demonstrate.run)] if needs_demos else []),
        *agent_steps,
        *[Step(f"{paper_eval}{eval_suffix(b)}", "eval", evaluate.run, {"evaluate": {"bank": b}}) for b in banks],
        *peer_steps,
    ]


def status(cfg, step: Step) -> tuple[str, list[str]]:
    """``(state, reasons)``: state is ``complete``, ``resume`` (unfinished, inputs unchanged), ``fresh`` (nothing
    there) or ``stale`` (reasons say what changed). The collection checks its own settings when it runs."""
    done = artifacts.marker(cfg, step.kind, step.agent).exists()
    directory = artifacts.output_dir(cfg, step.kind, step.agent)
    if step.kind in ("collect", "demos"):
        started = directory.is_dir() and any(directory.iterdir())
        return ("complete" if done else "resume" if started else "fresh"), []
    if not directory.exists():
        return "fresh", []
    recorded = artifacts.read_provenance(directory)
    if recorded is None and not done and step.kind != "eval" and not (directory / "last.pt").exists():
        return "fresh", []  # a directory a run created but never wrote to
    current = artifacts.provenance(cfg, step.kind, step.agent)
    reasons = artifacts.differences(recorded, current, artifacts.legacy_identities(artifacts.dataset_manifests(cfg)))
    if done and step.kind != "eval":  # a finished run's checkpoints changed after it finished
        reasons += artifacts.changed_outputs(directory)
    if reasons:
        return "stale", reasons
    return ("complete" if done else "resume"), []


PRODUCED_BY = {"rollouts": "collect", "vae": "vae", "rnn": "rnn", "demos": "demos"}  # a provenance input -> its step


def plan(cfg) -> list[dict]:
    """What ``run`` would do now, step by step, running nothing: each step's state (``status``; ``after`` for a step
    complete now whose input a step before it will rebuild or finish, so that it is checked again then) with the
    reasons, and the wall time ``pipeline.json`` recorded for it (so far, for a step interrupted and not finished)."""
    timings = _timings(cfg)
    planned = steps(cfg)
    step_of = {**PRODUCED_BY, **{s.agent.key: s.name for s in planned if s.agent is not None}}
    to_run: set[str] = set()
    rows = []
    for step in planned:
        stage_cfg = OmegaConf.merge(cfg, {"resume": True}, step.changes)
        state, reasons = status(stage_cfg, step)
        if state == "complete" and step.kind not in ("collect", "demos"):
            inputs = artifacts.provenance(stage_cfg, step.kind, step.agent)["inputs"]
            runs_first = {step_of[name] for name in inputs if step_of.get(name) in to_run}
            first = [s.name for s in planned if s.name in runs_first]  # in the order they run
            if first:
                state, reasons = "after", [f"checked again once {', '.join(first)} ran"]
        if state != "complete":
            to_run.add(step.name)
        record = timings.get(step.name, {})
        took = record.get("wall_s") if state == "complete" or record.get("complete") is False else None
        rows.append({"step": step.name, "state": state, "reasons": reasons, "wall_s": took, "estimate_s": None})
    for row in rows:
        if row["state"] in ("fresh", "stale", "resume"):
            row["estimate_s"] = _estimate(row, timings)
    return rows


def _estimate(row: dict, timings: dict) -> float | None:
    """A step's time still to go by its finished seeds: the median of their recorded times (a resumed step less its
    time so far); None when no other seed of it has finished."""
    stage = re.sub(r"/seed\d+$", "", row["step"])
    walls = [
        t["wall_s"]
        for name, t in timings.items()
        if name != row["step"] and re.sub(r"/seed\d+$", "", name) == stage and t.get("complete", True)
    ]
    if not walls:
        return None
    return max(0.0, float(np.median(walls)) - (row["wall_s"] or 0.0))


def plan_text(rows: list[dict]) -> str:
    width = max(len(r["step"]) for r in rows)
    lines = []
    for r in rows:
        took = "" if r["wall_s"] is None else f"{r['wall_s']:.0f} s" + ("" if r["state"] == "complete" else " so far")
        to_go = "" if r["estimate_s"] is None else f"~{r['estimate_s'] / 60:.0f} min to go"
        notes = "; ".join([*([to_go] if to_go else []), *r["reasons"]])
        lines.append(f"  {r['step']:<{width}}  {r['state']:<8}  {took:>14}  {notes}".rstrip())
    done = [r for r in rows if r["state"] == "complete"]
    recorded = sum(r["wall_s"] or 0 for r in done)
    left = [r for r in rows if r["state"] != "complete"]
    known = [r["estimate_s"] for r in left if r["estimate_s"] is not None]
    summary = f"  {len(done)} of {len(rows)} steps complete ({recorded:.0f} s recorded); {len(left)} to run"
    if known:
        summary += (
            f": ~{sum(known) / 3600:.1f} h for the {len(known)} whose other seeds finished (the median of their "
            f"times), {len(left) - len(known)} with none to go by"
        )
    lines.append(summary)
    return "\n".join(lines)


def _timings(cfg) -> dict:
    path = artifacts.runs_root(cfg) / "pipeline.json"
    return json.loads(path.read_text()) if path.exists() else {}


def run(cfg) -> dict:
    validate(cfg)
    if cfg.plan:
        rows = plan(cfg)
        log.info("[pipeline] plan=true: what a run would do now; nothing runs\n%s", plan_text(rows))
        return {"plan": rows}
    launcher.check_reachable(cfg)  # after the plan, which needs no SLURM; refused before the lock is taken
    with writer_lock(artifacts.runs_root(cfg), "one experiment's pipeline"):
        return _run_steps(cfg)


def _run_steps(cfg) -> dict:
    timing_path = artifacts.runs_root(cfg) / "pipeline.json"
    timings = _timings(cfg)
    t_all = time.perf_counter()
    planned = steps(cfg)
    states: dict[str, str] = {}

    def prepare(step: Step):
        """The step's config when it has to run (a stale one set aside first); None when it is complete."""
        stage_cfg = OmegaConf.merge(cfg, {"resume": True}, step.changes)
        state, reasons = status(stage_cfg, step)
        states[step.name] = state
        if state == "complete":
            log.info(
                "[pipeline] %s: complete (%s), skipped", step.name, artifacts.marker(stage_cfg, step.kind, step.agent)
            )
            return None
        if state == "stale":  # set aside under the stage's own lock: no hand-run writer is inside it
            with writer_lock(artifacts.output_dir(stage_cfg, step.kind, step.agent), f"the {step.name} step"):
                moved = artifacts.retire(stage_cfg, artifacts.output_dir(stage_cfg, step.kind, step.agent))
            log.info("[pipeline] %s: stale (%s); set aside in %s, rebuilding", step.name, "; ".join(reasons), moved)
        else:
            log.info("[pipeline] %s: running", step.name)
        return stage_cfg

    def record(step: Step, outcome: dict) -> None:
        """Add a step's run (``wall_s``, ``peak_rss_mb``, ``stopped``) to its record in ``pipeline.json``."""
        # an interrupted step's record holds its time so far; resumed, the step adds to it
        state = states[step.name]
        before = timings.get(step.name, {}) if state == "resume" else {}
        before = before if before.get("complete") is False else {}
        timings[step.name] = {
            "wall_s": round(before.get("wall_s", 0.0) + outcome["wall_s"], 1),
            "peak_rss_mb": round(max(before.get("peak_rss_mb", 0.0), outcome["peak_rss_mb"]), 1),
            "scale": OmegaConf.select(cfg, "scale_name", default=None),
            "invocations": before.get("invocations", 0) + 1,
            "complete": not outcome["stopped"],
            # resumed from a part that no record times (a process killed outright): wall_s is a lower bound
            "untimed_part": bool(before.get("untimed_part")) if before else state == "resume",
        }
        atomic_write_text(timing_path, json.dumps(timings, indent=2))

    if cfg.launcher == "inline":
        for step in planned:
            stage_cfg = prepare(step)
            if stage_cfg is None:
                continue
            t0 = time.perf_counter()
            with PeakMemory() as mem:
                result = step.run(stage_cfg)
            stopped = isinstance(result, dict) and bool(result.get("stopped"))
            record(step, {"wall_s": time.perf_counter() - t0, "peak_rss_mb": mem.peak_mb, "stopped": stopped})
            if stopped:
                log.info("[pipeline] %s was interrupted; rerun the pipeline to continue.", step.name)
                return timings
    elif not launcher.launch(cfg, planned, prepare, record):
        log.info("[pipeline] a step was interrupted; rerun the pipeline to continue.")
        return timings
    evaluations = [artifacts.eval_dir(OmegaConf.merge(cfg, s.changes)) for s in planned if s.kind == "eval"]
    log.info(
        "[pipeline] done in %.0f s (this run). Stage times: %s\n%s  TensorBoard: .venv/bin/tensorboard --logdir %s",
        time.perf_counter() - t_all,
        timing_path,
        "".join(f"  tables: {ev / 'tables.md'}\n" for ev in evaluations),
        cfg.paths.runs,
    )
    return timings


main = hydra_main("pipeline")(run)

if __name__ == "__main__":
    main()
