"""Evaluation on the seeded test bank: straight-line braking, the privileged planner and every trained agent.

    python -m worldmodel.evaluate experiment=NAME scale=...

The bank (DESIGN.md section 6; ``envs.test_bank``) sweeps hazard kind x TTC x speed with ``evaluate.per_cell``
seeded scenarios per cell; every policy sees exactly the same scenarios. Writes ``runs/NAME/eval/``:
``results.csv`` (one row per scenario and policy), ``summary.json``, ``tables.md`` (paper Tables I-III),
``heatmaps.png`` (Fig. 5 layout) and the same figures in TensorBoard.

Policies: ``evaluate.policies`` names the scripted ones (``braking``, the floor, is required; ``oracle`` is the
privileged planner of ``envs.planner``, the ceiling), and every agent under ``runs/NAME/agent_*/seed*/`` is added;
its rows carry the training seed in ``policy_seed`` so seed sweeps report mean and spread over seeds.

Straight-line braking and the planner run without the camera (outcomes are identical with it on, and it is ~10x faster).
Scenarios are spread over ``evaluate.num_workers`` processes in fixed chunks; every scenario is independent and
deterministic, so the rows are identical to a single-process run (tested).
"""
from __future__ import annotations

import time
from pathlib import Path

from .common import StageError, hydra_main, positive, runs_dir, set_threads
from .train_agent import trained_agents

ROW_META = ("policy", "policy_seed", "scenario_id", "hazard", "ttc", "speed", "seed")
SCRIPTED = ("braking", "oracle")


def eval_dir(cfg) -> Path:
    return runs_dir(cfg, "eval")


def bank(cfg):
    from envs import test_bank

    e = cfg.evaluate
    return test_bank(ttcs=tuple(e.ttcs), speeds=tuple(e.speeds), hazards=tuple(e.hazards), per_cell=int(e.per_cell),
                     seed=int(e.bank_seed))


def run_policy(env, policy, entries, desc: str | None = None, policy_seed: int = 0) -> list[dict]:
    """Roll ``policy`` through every bank entry; one row per scenario with the paper's section IV-C metrics.
    A policy with ``bind(env)`` (the privileged planner) is handed the env after each reset."""
    from tqdm import tqdm

    rows = []
    for entry in tqdm(entries, desc=desc or policy.name, unit="scenario", disable=desc is False):
        obs, info = env.reset(options={"scenario": entry.spec})
        policy.reset(entry.spec.seed)
        if hasattr(policy, "bind"):
            policy.bind(env)
        while True:
            obs, _, terminated, truncated, info = env.step(policy.act(obs, info))
            if terminated or truncated:
                break
        o = info["outcome"]
        rows.append({"policy": policy.name, "policy_seed": policy_seed, "scenario_id": entry.scenario_id, "hazard": entry.hazard,
                     "ttc": entry.ttc, "speed": entry.speed, "seed": entry.spec.seed,
                     **{k: o[k] for k in ("pedestrian_collision", "vehicle_collision", "static_collision",
                                          "lane_departure", "n_pedestrians_hit", "pedestrian_injury",
                                          "occupant_injury", "ego_occupant_injury", "speed_at_collision", "steps",
                                          "return_r1", "return_r2")}})
    return rows


_WORKER: dict = {}


def make_oracle(cfg):
    from envs import DT
    from envs.planner import PrivilegedPlanner

    o = cfg.evaluate.oracle
    return PrivilegedPlanner(replan_every=max(1, round(float(o.replan_every_s) / DT)), pedals=list(o.pedals),
                             steers=list(o.steers), delays_s=list(o.delays_s), lane_change_s=list(o.lane_change_s))


def _policy_for(cfg, name: str):
    from envs import StraightLineBraking

    from .agent_obs import LearnedPolicy
    from .train_agent import load_actor, load_world_model

    if name == "braking":
        return StraightLineBraking()
    if name == "oracle":
        return make_oracle(cfg)
    reward, seed = parse_agent(name)
    actor, _ = load_actor(cfg, reward, seed=seed)
    return LearnedPolicy(f"agent_{reward}", load_world_model(cfg), actor)


def agent_key(reward: str, seed: int) -> str:
    """How evaluation names one trained agent: ``agent_r1/seed0``."""
    return f"agent_{reward}/seed{seed}"


def parse_agent(key: str) -> tuple[str, int]:
    name, seed = key.split("/seed")
    return name.removeprefix("agent_"), int(seed)


def _run_chunk(task) -> list[dict]:
    """Worker side: (config, policy name, entries) -> rows. Env and policy are built once per process."""
    import torch
    from omegaconf import OmegaConf

    from .train_agent import make_env

    cfg_dict, name, entries = task
    torch.set_num_threads(1)
    key = name
    if key not in _WORKER:
        cfg = OmegaConf.create(cfg_dict)
        _WORKER[key] = (make_env(cfg, camera=name not in SCRIPTED), _policy_for(cfg, name))
    env, policy = _WORKER[key]
    return run_policy(env, policy, entries, desc=False, policy_seed=0 if name in SCRIPTED else parse_agent(name)[1])


def evaluate_policy(cfg, name: str, entries, workers: int) -> list[dict]:
    """Rows of one policy over ``entries``, in bank order, using ``workers`` processes."""
    import multiprocessing as mp

    from omegaconf import OmegaConf
    from tqdm import tqdm

    cfg_dict = OmegaConf.to_container(cfg, resolve=True)
    chunk = max(1, min(25, len(entries) // (4 * max(1, workers)) or 1))
    tasks = [(cfg_dict, name, entries[i: i + chunk]) for i in range(0, len(entries), chunk)]
    rows: list[dict] = []
    with tqdm(total=len(entries), desc=name, unit="scenario") as bar:
        if workers <= 1:
            for t in tasks:
                rows += _run_chunk(t)
                bar.update(len(t[2]))
        else:
            with mp.get_context("spawn").Pool(workers) as pool:
                for part in pool.imap(_run_chunk, tasks):
                    rows += part
                    bar.update(len(part))
    return rows


def validate_config(cfg) -> None:
    positive(cfg.evaluate, "per_cell", "num_workers", where="evaluate")
    if not cfg.evaluate.ttcs or not cfg.evaluate.speeds or not cfg.evaluate.hazards:
        raise StageError("config evaluate.ttcs, evaluate.speeds and evaluate.hazards must not be empty")
    for key in ("ttcs", "speeds"):
        if any(v <= 0 for v in cfg.evaluate[key]):
            raise StageError(f"config evaluate.{key}={list(cfg.evaluate[key])} must all be positive")
    policies = list(cfg.evaluate.policies)
    if "braking" not in policies or any(p not in SCRIPTED for p in policies):
        raise StageError(f"config evaluate.policies={policies} must include 'braking' (the baseline) and may add "
                         f"'oracle'; trained agents are found by themselves")
    if "oracle" in policies:
        if float(cfg.evaluate.oracle.replan_every_s) <= 0:
            raise StageError(f"config evaluate.oracle.replan_every_s={cfg.evaluate.oracle.replan_every_s} must be > 0")
        try:
            make_oracle(cfg)
        except ValueError as err:
            raise StageError(f"config evaluate.oracle: {err}") from None


def run(cfg) -> dict:
    from .report import write_report, write_results_csv
    from .training import tensorboard

    validate_config(cfg)
    set_threads(1)   # one decision at a time: a single thread is fastest for batch-1 inference
    entries = bank(cfg)
    out = eval_dir(cfg)
    t0 = time.perf_counter()

    workers = int(cfg.evaluate.num_workers)
    agents = [agent_key(r, s) for r, s in trained_agents(cfg)]
    for key in agents:   # fail fast on a broken checkpoint, before any scenario runs
        _policy_for(cfg, key)
    rows = []
    for key in [p for p in SCRIPTED if p in cfg.evaluate.policies] + agents:
        rows += evaluate_policy(cfg, key, entries, workers)
    if not agents:
        print(f"[eval] no trained agents under {Path(cfg.paths.runs)}; evaluating braking only. "
              "Train one with `python -m worldmodel.train_agent experiment=... reward=r1`.")

    write_results_csv(rows, out / "results.csv")
    writer = tensorboard(out)
    summary = write_report(rows, out, tb_writer=writer)
    writer.close()
    n_policies = len(agents) + len(list(cfg.evaluate.policies))
    print(f"[eval] {len(entries)} scenarios x {n_policies} policies in {time.perf_counter() - t0:.0f} s. "
          f"Tables: {out / 'tables.md'}  Heatmaps: {out / 'heatmaps.png'}")
    return summary


main = hydra_main("evaluate")(run)

if __name__ == "__main__":
    main()
