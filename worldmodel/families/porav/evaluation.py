"""The paper's family's evaluation (``python -m worldmodel.evaluate``, ``evaluate.family`` unset) on a seeded
scenario bank: straight-line braking, the privileged planner and every trained agent.

The bank (docs/design.md §6; ``envs.scenario_bank``), a validation bank unless ``evaluate.bank=test``, sweeps
hazard kind x TTC x speed with ``evaluate.per_cell`` seeded scenarios per cell; every policy sees exactly the same
scenarios. Writes ``runs/NAME/eval/`` (``eval_test/`` on the test bank):
``results.csv`` (one row per scenario and policy), ``summary.json``, ``tables.md`` (paper Tables I-III),
``heatmaps.png`` (Fig. 5 layout) and the same figures in TensorBoard.

Policies: ``evaluate.policies`` names the scripted ones (``braking``, the floor, is required; ``oracle`` is the
privileged planner of ``envs.planner``, the ceiling), and every agent under ``runs/NAME/agent_*/seed*/`` is added;
its rows carry the training seed in ``policy_seed`` so seed sweeps report mean and spread over seeds.

Straight-line braking and the planner run without the camera (outcomes are identical with it on, and it is ~10x faster);
the camera's cap ``oracle_pixelsK``, which waits for the hazard to cover K pixels of the frame, runs with it.
Scenarios are spread over ``evaluate.num_workers`` processes in fixed chunks; every scenario is independent and
deterministic, so the rows are identical to a single-process run (tested).
"""

from __future__ import annotations

import logging

from ... import artifacts
from ...banks import draw_seed
from ...common import make_env, resolve_workers, worker_pool
from ...config import SCRIPTED_POLICIES
from ...policies import EXACT_CHOOSER, NO_MODELS, env_overrides, policy_for
from ...report import OUTCOME_COLUMNS, render_report, write_results_csv
from ..common import Driven, evaluation
from . import FAMILY

log = logging.getLogger(__name__)


def bank(cfg):
    """The scenarios of ``evaluate.bank``: a validation bank, or the sealed test bank (the same grid, drawn from
    another seed; worldmodel/banks.py). ``cfg``: the typed config (``validate``), or the composed one, whose values
    have the same types."""
    e = cfg.evaluate
    return bank_of(e, draw_seed(e.bank, FAMILY.name, e.validation_seed))


def bank_of(e, seed: int):
    """The grid of the ``evaluate`` section ``e`` drawn from ``seed``."""
    from envs import scenario_bank

    return scenario_bank(
        ttcs=tuple(e.ttcs), speeds=tuple(e.speeds), hazards=tuple(e.hazards), per_cell=e.per_cell, seed=int(seed)
    )


def run_policy(
    env, policy, entries, desc: str | bool | None = None, policy_seed: int = 0, models: dict | None = None
) -> list[dict]:
    """Roll ``policy`` through every bank entry; one row per scenario with the paper's section IV-C metrics and
    the short hashes of the models behind the policy (empty for scripted ones)."""
    from tqdm import tqdm

    from envs.rollout import rollout

    rows = []
    for entry in tqdm(entries, desc=desc or policy.name, unit="scenario", disable=desc is False):
        o = rollout(env, policy, entry.spec).outcome
        rows.append(
            {
                "policy": policy.name,
                "policy_seed": policy_seed,
                "scenario_id": entry.scenario_id,
                "hazard": entry.hazard,
                "ttc": entry.ttc,
                "speed": entry.speed,
                "seed": entry.spec.seed,
                **{k: o[k] for k in OUTCOME_COLUMNS},
                **(models or NO_MODELS),
            }
        )
    return rows


_WORKER: dict = {}  # a pool worker's env and policy, built once per policy: the pool lives for one evaluation


def _build(cfg_dict, name: str):
    """(env, policy, seed, models) for policy ``name``, on one torch thread."""
    import torch
    from omegaconf import OmegaConf

    torch.set_num_threads(1)
    cfg = OmegaConf.create(cfg_dict)
    policy, seed, models = policy_for(cfg, name)
    # the scripted policies read the true state, not the frame, except the camera's cap (oracle_pixelsK); so does an
    # agent trained on it (obs=privileged): a policy that says whether it needs the camera is taken at its word
    camera = getattr(policy, "needs_camera", name not in (*SCRIPTED_POLICIES, EXACT_CHOOSER))
    return make_env(cfg, camera=camera, **env_overrides(policy)), policy, seed, models


def _run_chunk(task) -> list[dict]:
    """Pool worker side: (config, policy name, entries) -> rows. The chunks come policy by policy, so a worker keeps
    the policy it is running and lets the one before it go."""
    cfg_dict, name, entries = task
    if name not in _WORKER:
        for env, *_ in _WORKER.values():
            env.close()
        _WORKER.clear()
        _WORKER[name] = _build(cfg_dict, name)
    env, policy, seed, models = _WORKER[name]
    return run_policy(env, policy, entries, desc=False, policy_seed=seed, models=models)


def evaluate_policy(cfg, name: str, entries, workers: int) -> list[dict]:
    """Rows of one policy over ``entries``, in bank order, using ``workers`` processes."""
    return evaluate_policies(cfg, [name], entries, workers)[name]


def evaluate_policies(cfg, names: list[str], entries, workers: int) -> dict[str, list[dict]]:
    """Each policy's rows over ``entries``, in bank order, using ``workers`` processes. One pool serves every policy
    (starting one per policy cost each worker its imports and the world model's digests again), fed in chunks
    policy after policy."""
    from omegaconf import OmegaConf
    from tqdm import tqdm

    cfg_dict = OmegaConf.to_container(cfg, resolve=True)
    chunk = max(1, min(25, len(entries) // (4 * max(1, workers)) or 1))
    tasks = [(cfg_dict, name, entries[i : i + chunk]) for name in names for i in range(0, len(entries), chunk)]
    rows: dict[str, list[dict]] = {name: [] for name in names}
    with tqdm(total=len(entries) * len(names), desc="evaluate", unit="scenario") as bar:
        if workers <= 1:
            for name in names:
                bar.set_postfix_str(name)
                # built afresh on every call, never cached in this process: a checkpoint may have been replaced
                # (retrained, or rebuilt by the pipeline) since the last evaluation here
                env, policy, seed, models = _build(cfg_dict, name)
                try:
                    for i in range(0, len(entries), chunk):
                        part = entries[i : i + chunk]
                        rows[name] += run_policy(env, policy, part, desc=False, policy_seed=seed, models=models)
                        bar.update(len(part))
                finally:
                    env.close()
        else:
            with worker_pool(workers) as pool:
                for (_, name, _), part in zip(tasks, pool.imap(_run_chunk, tasks)):
                    bar.set_postfix_str(name, refresh=False)
                    rows[name] += part
                    bar.update(len(part))
    return rows


def headline(summary: dict) -> dict[str, str]:
    """Each policy's headline figure, its seeds pooled: the share of the achievable improvement and the mean total
    severe-injury risk per scenario."""
    shares = summary.get("achievable_share", {}).get("policies", {})
    out = {}
    for policy, entry in summary["policies"].items():
        risk = entry["overall"].get("total_severe_injury")
        text = "risk n/a" if risk is None else f"risk {100 * risk:.2f} %"
        share = shares.get(policy, {}).get("overall")
        if share is not None and policy not in ("braking", "oracle"):
            text = f"share {share:.1f} %, {text}"
        out[policy] = text
    return out


def evaluate(cfg) -> dict:
    """Every scripted policy of ``evaluate.policies`` and every trained agent of the family on its bank (the
    evaluation skeleton, ``families.common.evaluation``)."""
    return evaluation(cfg, FAMILY.name, None, drive, report, FAMILY.preset, write=write)


def drive(cfg, e) -> Driven:
    """Every policy through the bank of ``e`` (``evaluate``, its validation seed drawn for the bank), in
    ``evaluate.num_workers`` processes."""
    entries = bank_of(e, e.validation_seed)
    agents = [a.key for a in artifacts.trained_agents(cfg)]
    for key in agents:  # fail fast on a broken or stale checkpoint, before any scenario runs
        policy_for(cfg, key)
    names = [p for p in SCRIPTED_POLICIES if p in e.policies] + agents
    rows = evaluate_policies(cfg, names, entries, resolve_workers(e.num_workers))
    return Driven([r for policy_rows in rows.values() for r in policy_rows], agents, len(entries), len(names))


def write(out, rows: list[dict]) -> None:
    write_results_csv(rows, out / "results.csv")  # its rows carry their models' hashes (policies.policy_for)


def report(cfg, e, done: Driven, out) -> tuple[dict, dict]:
    """``tables.md`` (paper Tables I-III), ``heatmaps.png`` (Fig. 5 layout) and both in TensorBoard."""
    from ...training import tensorboard

    writer = tensorboard(out)
    summary = render_report(done.rows, out, tb_writer=writer)
    writer.close()
    return summary, headline(summary)
