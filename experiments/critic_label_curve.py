"""Can the counterfactual critic tell, from what the actor sees, which shift beats braking, and do more labels help?

    python -m experiments.critic_label_curve experiment=quick scale=quick [--episodes 4000] [--held-out 600]
        [--sizes 500 1000 2000 3400] [--seeds 0 1 2] [--boot 2000]

The counterfactual actor (``worldmodel/counterfactual.py``) can only be as good as its critic's choice among shifts.
This measures that choice offline, on labelled decision states the critic never saw. Round 0's labels (straight-line
braking's states, ``agent.counterfactual.proposals`` shifts each with their exact R2 cost; stored where training
stores them, labelled here if missing) are split by episode: the last ``--held-out`` episodes are held out, and
critics (``counterfactual.fit_critic``, the experiment's settings) are fitted on the first ``n`` episodes for each
``n`` in ``--sizes``, reading either the world model's view (as the actor does; the experiment's world model) or the
true state (``envs/privileged.py``). On every held-out state the critic picks the labelled shift of lowest predicted
cost (members' mean); with a margin, it keeps braking unless that shift is predicted to save more than the margin.

Columns, per view, labelled episodes and critic seed:

* ``Spearman``: the critic's held-out rank correlation with the exact costs (``counterfactual.critic_figures``);
* ``captured %``: 100 x (braking's exact cost - the picked shifts' exact cost) / (braking's - the cheapest labelled
  shift's), over the held-out states: 0 = braking, 100 = always the cheapest of the labelled shifts; negative where
  acting on the critic loses to braking. With a bootstrap 95 % interval over held-out episodes;
* ``switches %``: the share of held-out states where the pick is not braking.

Only round 0's labels are used (no actor drives), and no scenario bank: nothing here touches a validation or test
bank. Writes ``runs/NAME/critic_label_curve/critic_label_curve.md`` (the table printed here) and ``.csv``.
"""

from __future__ import annotations

import argparse
import csv
import logging
import time

import numpy as np
import torch

from worldmodel import artifacts, counterfactual, counterfactual_labels, loading
from worldmodel.config import compose

MARGINS = (0.0, 0.01)  # R2 units of predicted saving a switch must exceed; 0.01 is what "the decision matters" means


def captured(picked: np.ndarray, brake: np.ndarray, best: np.ndarray) -> float:
    """The share (%) of braking's excess over the cheapest labelled shift that the picks remove."""
    gap = brake.mean() - best.mean()
    return float(100.0 * (brake.mean() - picked.mean()) / gap) if gap > 0 else float("nan")


def picks(predicted: np.ndarray, u: np.ndarray, margin: float) -> np.ndarray:
    """Per state, the index of the labelled shift the critic acts on: its cheapest predicted, unless braking's
    predicted cost is within ``margin`` of it (then braking's index)."""
    is_brake = ~u.any(axis=2)
    if not is_brake.any(axis=1).all():
        raise ValueError("every labelled state needs braking (u = 0) among its shifts")
    brake_index = is_brake.argmax(axis=1)
    rows = np.arange(len(predicted))
    best = predicted.argmin(axis=1)
    switch = predicted[rows, best] < predicted[rows, brake_index] - margin
    return np.where(switch, best, brake_index)


def summarise(predicted, u, costs, episode, margin: float, boot: int, seed: int = 0) -> dict:
    """``captured`` (with a bootstrap interval over episodes) and the switch share of acting on ``predicted``."""
    chosen = picks(predicted, u, margin)
    rows = np.arange(len(costs))
    picked = costs[rows, chosen]
    brake = costs[rows, (~u.any(axis=2)).argmax(axis=1)]
    best = costs.min(axis=1)
    episodes, index = np.unique(episode, return_inverse=True)
    sums = np.stack([np.bincount(index, weights=a, minlength=len(episodes)) for a in (picked, brake, best)])
    counts = np.bincount(index, minlength=len(episodes))
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(boot):
        e = rng.integers(0, len(episodes), len(episodes))
        p, b, o = sums[:, e].sum(1) / counts[e].sum()
        draws.append(100.0 * (b - p) / (b - o) if b > o else np.nan)
    low, high = np.nanpercentile(draws, [2.5, 97.5]) if boot else (np.nan, np.nan)
    return {
        "captured": captured(picked, brake, best),
        "low": float(low),
        "high": float(high),
        "switches": float(100.0 * (chosen != (~u.any(axis=2)).argmax(axis=1)).mean()),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. experiment=quick scale=quick")
    parser.add_argument("--episodes", type=int, default=4000, help="round-0 labelled episodes in all")
    parser.add_argument("--held-out", type=int, default=600, help="the last episodes, held out to measure")
    parser.add_argument("--sizes", type=int, nargs="+", default=[500, 1000, 2000, 3400], help="training episodes")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="critic seeds at the largest size")
    parser.add_argument("--boot", type=int, default=2000, help="bootstrap resamples of the held-out episodes")
    args = parser.parse_intermixed_args(argv)
    if args.held_out < 1 or max(args.sizes) > args.episodes - args.held_out or min(args.sizes) < 1:
        parser.error(f"--sizes must lie in [1, episodes - held-out] = [1, {args.episodes - args.held_out}]")
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = compose("train_agent", [*args.overrides, "reward=r2", "agent=counterfactual"])
    c = counterfactual_labels.cfg_counterfactual(cfg)
    data = counterfactual_labels.labels(cfg, 0, args.episodes, counterfactual_labels.labels_dir(cfg, 0))
    views = {
        "world model": counterfactual_labels.encode_states(loading.load_world_model(cfg), data, c.decisions),
        "true state": counterfactual_labels.privileged_states(data, c.decisions),
    }
    episode, u, costs = data["episode"], data["u"], data["costs"]
    held = episode >= args.episodes - args.held_out
    results = []
    for view, x in views.items():
        for n in sorted(args.sizes):
            for seed in args.seeds if n == max(args.sizes) else args.seeds[:1]:
                use = (episode < n) | held
                start = time.time()
                critic, figures = counterfactual.fit_critic(
                    x[use], u[use], costs[use], data["state"][use], held[use], c, seed, 0
                )
                predicted = counterfactual.critic_predict(critic, x[held], u[held])
                row = {"view": view, "episodes": n, "seed": seed, "spearman": figures["spearman"]}
                for margin in MARGINS:
                    s = summarise(predicted, u[held], costs[held], episode[held], margin, args.boot)
                    row.update({f"{k}@{margin:g}": v for k, v in s.items()})
                results.append(row)
                logging.info("%s, %d episodes, seed %d (%.0f s): %s", view, n, seed, time.time() - start, row)
    rows = np.arange(int(held.sum()))
    brake_cost = costs[held][rows, (~u[held].any(axis=2)).argmax(axis=1)]
    best_cost = costs[held].min(axis=1)
    lines = [
        f"Experiment {cfg.experiment}: round-0 labels of {args.episodes} braking episodes "
        f"({counterfactual_labels.labels_dir(cfg, 0)}), the last {args.held_out} held out: {int(held.sum())} decision "
        f"states, {c.proposals} labelled shifts each. Held out, braking costs {100 * brake_cost.mean():.2f} points "
        f"of R2 per state and the cheapest labelled shift {100 * best_cost.mean():.2f}.",
        "",
        "| critic reads | labelled episodes | critic seed | Spearman | "
        + " | ".join(f"captured % [95 % CI], margin {m:g} | switches %, margin {m:g}" for m in MARGINS)
        + " |",
        "|---|---:|---:|---:|" + "---:|---:|" * len(MARGINS),
    ]
    for r in results:
        cells = [
            f"{r[f'captured@{m:g}']:.1f} [{r[f'low@{m:g}']:.1f}, {r[f'high@{m:g}']:.1f}] | {r[f'switches@{m:g}']:.0f}"
            for m in MARGINS
        ]
        head = f"| {r['view']} | {r['episodes']} | {r['seed']} | {r['spearman']:.2f} | "
        lines.append(head + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    out = artifacts.runs_root(cfg) / "critic_label_curve"
    out.mkdir(parents=True, exist_ok=True)
    (out / "critic_label_curve.md").write_text(text)
    with open(out / "critic_label_curve.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(results[0]))
        writer.writeheader()
        writer.writerows(results)
    print(text)
    return 0


if __name__ == "__main__":
    torch.set_num_threads(2)
    raise SystemExit(main())
