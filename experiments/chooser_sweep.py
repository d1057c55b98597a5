"""Choosing the chooser's settings on the validation bank, exactly and without simulating.

    python -m experiments.chooser_sweep experiment=quick [--variants base,adv,ens5,...] [--seeds 0]
    python -m experiments.chooser_sweep experiment=quick env.tele_fov_deg=30 --variants maskauxcost,teleauxcost

The chooser brakes until it switches, so its cost on a scenario follows from the exact costs of every candidate at
every step of braking (``worldmodel.chooser.policy_cost``, tested equal to the simulated episode). This labels the
validation bank's scenarios once (``data/NAME/chooser_labels/validation-*/``, ~4 min at quick scale), then fits
each scorer variant on the training labels and prints, per variant and switching margin, the whole-bank share of
the achievable improvement on the validation bank (the planner's cost from ``runs/NAME/ablation/rows_oracle.csv``,
which ``experiments.ablation`` writes), the mean R2 cost per scenario, and how often the chooser switches. The test
bank is never touched. Writes ``runs/NAME/chooser_sweep/sweep.md``.
"""

from __future__ import annotations

import argparse
import logging

import numpy as np
import torch
from omegaconf import OmegaConf

from worldmodel import artifacts, chooser, loading
from worldmodel.config import compose
from worldmodel.report import _mean, read_results_csv

log = logging.getLogger("chooser_sweep")
MARGINS = (0.0, 0.01, 0.02, 0.03, 0.05, 0.08, 0.12, 0.5, 1.0, 2.0)  # the last ones for logits
# name -> (world-model input overrides, agent.chooser overrides)
VARIANTS: dict[str, tuple[list[str], dict]] = {
    "base": ([], {}),
    "adv": ([], {"target": "advantage"}),
    "ens5": ([], {"ensemble": 5}),
    "advens5": ([], {"target": "advantage", "ensemble": 5}),
    "advens5wm": (["agent.frame_view=false"], {"target": "advantage", "ensemble": 5}),
    "advens5half": (["agent.chooser.episodes=1500"], {"target": "advantage", "ensemble": 5}),
    "advens5fifth": (["agent.chooser.episodes=600"], {"target": "advantage", "ensemble": 5}),
    "mask": ([], {"target": "advantage", "mask_view": True, "steps": 3000}),
    "maskcost": ([], {"mask_view": True, "steps": 3000}),
    "pol": ([], {"target": "policy"}),
    "polmask": ([], {"target": "policy", "mask_view": True, "steps": 3000}),
    "maskaux": ([], {"target": "advantage", "mask_view": True, "steps": 3000, "aux_weight": 1.0}),
    "aux": ([], {"target": "advantage", "aux_weight": 1.0}),
    "aux5": ([], {"target": "advantage", "aux_weight": 5.0}),
    "auxens5": ([], {"target": "advantage", "aux_weight": 1.0, "ensemble": 5}),
    "auxcost": ([], {"aux_weight": 1.0}),
    "privileged": ([], {"target": "advantage"}),
    "maskens3": ([], {"target": "advantage", "mask_view": True, "steps": 3000, "ensemble": 3}),
    # the band of the narrow second camera (run the sweep with env.tele_fov_deg=30, so the labels hold its frames)
    "maskauxcost": ([], {"mask_view": True, "steps": 3000, "aux_weight": 1.0}),
    "teleauxcost": ([], {"mask_view": True, "mask_camera": "tele", "steps": 3000, "aux_weight": 1.0}),
    "teleaux": (
        [],
        {"mask_view": True, "mask_camera": "tele", "steps": 3000, "aux_weight": 1.0, "target": "advantage"},
    ),
}


def first_switch(pred: np.ndarray, episode: np.ndarray, margin: float) -> np.ndarray:
    """Per episode, whether the chooser acting on ``pred`` switches at all."""
    out = []
    for e in np.unique(episode):
        p = pred[episode == e]
        out.append(bool(((p[:, :1] - p) > margin).any()))
    return np.asarray(out)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. experiment=quick")
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--seeds", default="0", help="training seeds (each its own labels)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(2)
    base = [*args.overrides, "reward=r2", "agent=chooser"]
    cfg = compose("train_agent", base)
    val = chooser.labels(cfg, "validation")
    y_val = val["costs"]
    braking = float(np.mean(y_val[np.r_[True, val["episode"][1:] != val["episode"][:-1]], 0]))
    exact = float(chooser.policy_cost(y_val, y_val, val["episode"], 0.0).mean())
    oracle_csv = artifacts.runs_root(cfg) / "ablation" / "rows_oracle.csv"
    oracle = _mean(read_results_csv(oracle_csv), "total_injury") if oracle_csv.exists() else float("nan")

    def share(cost: float) -> float:
        return 100 * (braking - cost) / (braking - oracle)

    lines = [
        f"Validation bank ({len(np.unique(val['episode']))} scenarios), mean R2 cost per scenario: braking "
        f"{100 * braking:.2f} %, planner {100 * oracle:.2f} %, the chooser on exact costs {100 * exact:.2f} % "
        f"(share {share(exact):.0f} %).",
        "",
        "| variant | seed | margin | share % | cost % | switches % |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    encoded: dict[str, tuple] = {}
    for name in [v for v in args.variants.split(",") if v]:
        inputs, settings = VARIANTS[name]
        for seed in [int(s) for s in args.seeds.split(",")]:
            vcfg = compose("train_agent", [*base, *inputs, f"seed={seed}"])
            c = OmegaConf.to_object(OmegaConf.merge(chooser.cfg_chooser(vcfg), settings))
            steps = chooser.decide_steps_for(c.decide_s)
            key = f"{inputs}-{seed}-{c.mask_view}-{c.mask_camera}-{name == 'privileged'}"
            if key not in encoded:
                train = chooser.labels(vcfg)
                if name == "privileged":  # the true hazard state instead of the camera: the learner's own bound
                    x, xv = (
                        np.concatenate([d["state"], d["speed"][:, None], d["t"][:, None] / steps], 1).astype(np.float32)
                        for d in (train, val)
                    )
                else:
                    encoder = loading.load_world_model(vcfg)
                    x = chooser.scorer_inputs(encoder, train, steps, bool(c.mask_view), c.mask_camera)
                    xv = chooser.scorer_inputs(encoder, val, steps, bool(c.mask_view), c.mask_camera)
                encoded[key] = (x, train, xv)
            x, train, xv = encoded[key]
            scorer, _ = chooser.fit_scorer(x, train["costs"], train["episode"], c, seed, state=train["state"])
            with torch.no_grad():
                pred = scorer(torch.from_numpy(xv)).numpy()
            for m in MARGINS:
                cost = float(chooser.policy_cost(pred, y_val, val["episode"], m).mean())
                switches = 100 * first_switch(pred, val["episode"], m).mean()
                lines.append(f"| {name} | {seed} | {m} | {share(cost):.0f} | {100 * cost:.2f} | {switches:.0f} |")
            log.info("\n".join(lines[-len(MARGINS) :]))
    out = artifacts.runs_root(cfg) / "chooser_sweep"
    out.mkdir(parents=True, exist_ok=True)
    text = "\n".join(lines) + "\n"
    (out / "sweep.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
