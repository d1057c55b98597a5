"""Evaluation on the seeded test bank: straight-line braking vs every trained agent of the experiment.

    python -m worldmodel.evaluate experiment=NAME scale=...

The bank (DESIGN.md section 6; ``envs.test_bank``) sweeps hazard kind x TTC x speed with ``evaluate.per_cell``
seeded scenarios per cell; every policy sees exactly the same scenarios. Writes ``runs/NAME/eval/``:
``results.csv`` (one row per scenario and policy), ``summary.json``, ``tables.md`` (paper Tables I-III),
``heatmaps.png`` (Fig. 5 layout) and the same figures in TensorBoard.

Straight-line braking runs without the camera (outcomes are identical with it on, and it is ~10x faster).
"""
from __future__ import annotations

import time
from pathlib import Path

from .common import StageError, hydra_main, positive, runs_dir, set_threads

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


def trained_agents(cfg) -> list[str]:
    return [r for r in ("r1", "r2") if (runs_dir(cfg, f"agent_{r}") / "last.pt").exists()]


def validate_config(cfg) -> None:
    positive(cfg.evaluate, "per_cell", where="evaluate")
    if not cfg.evaluate.ttcs or not cfg.evaluate.speeds or not cfg.evaluate.hazards:
        raise StageError("config evaluate.ttcs, evaluate.speeds and evaluate.hazards must not be empty")
    for key in ("ttcs", "speeds"):
        if any(v <= 0 for v in cfg.evaluate[key]):
            raise StageError(f"config evaluate.{key}={list(cfg.evaluate[key])} must all be positive")


def run(cfg) -> dict:
    from envs import StraightLineBraking

    from .agent_obs import LearnedPolicy
    from .report import write_report, write_results_csv
    from .train_agent import load_actor, load_world_model, make_env
    from .training import tensorboard

    validate_config(cfg)
    set_threads(1)   # one decision at a time: a single thread is fastest for batch-1 inference
    entries = bank(cfg)
    out = eval_dir(cfg)
    t0 = time.perf_counter()

    rows = []
    env = make_env(cfg, camera=False)
    rows += run_policy(env, StraightLineBraking(), entries)
    env.close()

    agents = trained_agents(cfg)
    if agents:
        env = make_env(cfg, camera=True)
        for reward in agents:
            actor, _ = load_actor(cfg, reward)
            policy = LearnedPolicy(f"agent_{reward}", load_world_model(cfg), actor)
            rows += run_policy(env, policy, entries)
        env.close()
    else:
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
