"""Evaluation on the seeded test bank: straight-line braking vs every trained agent of the experiment.

    python -m worldmodel.evaluate experiment=NAME scale=...

The bank (DESIGN.md section 6; ``envs.test_bank``) sweeps hazard kind x TTC x speed with ``evaluate.per_cell``
seeded scenarios per cell; every policy sees exactly the same scenarios. Writes ``runs/NAME/eval/``:
``results.csv`` (one row per scenario and policy), ``summary.json``, ``tables.md`` (paper Tables I-III),
``heatmaps.png`` (Fig. 5 layout) and the same figures in TensorBoard.

Straight-line braking runs without the camera (outcomes are identical with it on, and it is ~10x faster).
Scenarios are spread over ``evaluate.num_workers`` processes in fixed chunks; every scenario is independent and
deterministic, so the rows are identical to a single-process run (tested).
"""
from __future__ import annotations

import time
from pathlib import Path

from .common import StageError, hydra_main, positive, runs_dir, set_threads
from .train_agent import trained_agents

ROW_META = ("policy", "scenario_id", "hazard", "ttc", "speed", "seed")


def eval_dir(cfg) -> Path:
    return runs_dir(cfg, "eval")


def bank(cfg):
    from envs import test_bank

    e = cfg.evaluate
    return test_bank(ttcs=tuple(e.ttcs), speeds=tuple(e.speeds), hazards=tuple(e.hazards), per_cell=int(e.per_cell),
                     seed=int(e.bank_seed))


def run_policy(env, policy, entries, desc: str | None = None) -> list[dict]:
    """Roll ``policy`` through every bank entry; one row per scenario with the paper's section IV-C metrics."""
    from tqdm import tqdm

    rows = []
    for entry in tqdm(entries, desc=desc or policy.name, unit="scenario", disable=desc is False):
        obs, info = env.reset(options={"scenario": entry.spec})
        policy.reset(entry.spec.seed)
        while True:
            obs, _, terminated, truncated, info = env.step(policy.act(obs, info))
            if terminated or truncated:
                break
        o = info["outcome"]
        rows.append({"policy": policy.name, "scenario_id": entry.scenario_id, "hazard": entry.hazard,
                     "ttc": entry.ttc, "speed": entry.speed, "seed": entry.spec.seed,
                     **{k: o[k] for k in ("pedestrian_collision", "vehicle_collision", "static_collision",
                                          "lane_departure", "n_pedestrians_hit", "pedestrian_injury",
                                          "occupant_injury", "ego_occupant_injury", "speed_at_collision", "steps",
                                          "return_r1", "return_r2")}})
    return rows


_WORKER: dict = {}


def _policy_for(cfg, name: str):
    from envs import StraightLineBraking

    from .agent_obs import LearnedPolicy
    from .train_agent import load_actor, load_world_model

    if name == "braking":
        return StraightLineBraking()
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
        _WORKER[key] = (make_env(cfg, camera=name != "braking"), _policy_for(cfg, name))
    env, policy = _WORKER[key]
    return run_policy(env, policy, entries, desc=False)


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
    rows = evaluate_policy(cfg, "braking", entries, workers)
    for key in agents:
        rows += evaluate_policy(cfg, key, entries, workers)
    if not agents:
        print(f"[eval] no trained agents under {Path(cfg.paths.runs)}; evaluating braking only. "
              "Train one with `python -m worldmodel.train_agent experiment=... reward=r1`.")

    write_results_csv(rows, out / "results.csv")
    writer = tensorboard(out)
    summary = write_report(rows, out, tb_writer=writer)
    writer.close()
    print(f"[eval] {len(entries)} scenarios x {1 + len(agents)} policies in {time.perf_counter() - t0:.0f} s. "
          f"Tables: {out / 'tables.md'}  Heatmaps: {out / 'heatmaps.png'}")
    return summary


main = hydra_main("evaluate")(run)

if __name__ == "__main__":
    main()
