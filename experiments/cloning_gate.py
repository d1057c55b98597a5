"""The feasibility gate: how much of the planner's decisions the world model's view carries.

    python -m experiments.cloning_gate experiment=quick demos.episodes=500

Encodes the planner demonstrations (``worldmodel.demonstrate``) through the frozen world model exactly as the agent
sees them, with the braking anchor and grip steering, then fits students on the store's train split and reports the
mean |mu(s) - a|^2 on its held-out split for: the zero action (braking), the best constant action, a regularised
MLP (256-256, dropout 0.5, AdamW weight decay 0.1, lr 3e-4, the best of checks every 250 of 4000 minibatches) on
[z, zhat, speed], on z and speed, on speed alone, on the raw frame's hazard profiles (``agent.frame_view``,
``envs/views.py``) with and without the latents, and on 1/4 and 1/2 of the training episodes. Then, over the
episodes in which the teacher swerves, how often a small classifier tells from the input at the first swerving
frame which side it swerves to (5-fold cross-validated). Prints both tables.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from worldmodel import imitation, loading
from worldmodel.action_map import ActionMap
from worldmodel.common import set_threads
from worldmodel.config import compose


def fit(x, y, xv, yv, steps: int = 4000, seed: int = 0) -> float:
    """The best held-out error of a regularised MLP student trained on (x, y)."""
    torch.manual_seed(seed)
    m, s = x.mean(0), x.std(0) + 1e-3
    net = torch.nn.Sequential(
        torch.nn.Linear(x.shape[1], 256), torch.nn.ReLU(), torch.nn.Dropout(0.5),
        torch.nn.Linear(256, 256), torch.nn.ReLU(), torch.nn.Dropout(0.5),
        torch.nn.Linear(256, 2),
    )  # fmt: skip
    opt = torch.optim.AdamW(net.parameters(), lr=3e-4, weight_decay=0.1)
    g = torch.Generator().manual_seed(seed)
    best = float("inf")
    for k in range(steps):
        idx = torch.randint(0, len(x), (64,), generator=g)
        net.train()
        loss = ((torch.tanh(net((x[idx] - m) / s)) - y[idx]) ** 2).sum(-1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if (k + 1) % 250 == 0:
            net.eval()
            with torch.no_grad():
                best = min(best, ((torch.tanh(net((xv - m) / s)) - yv) ** 2).sum(-1).mean().item())
    return best


def first_swerves(cfg, actions: np.ndarray, split: str) -> np.ndarray:
    """Row indices (into the split's transitions, stored episode by episode) of each episode's first frame with
    |u_steer| > 0.3: where the teacher commits to a side."""
    store = loading.open_demos(cfg)
    lengths = [int(store.attrs(i)["n_steps"]) for i in sorted(store.episodes(split))]
    store.close()
    rows, start = [], 0
    for n in lengths:
        k = np.flatnonzero(np.abs(actions[start : start + n, 0]) > 0.3)
        if len(k):
            rows.append(start + k[0])
        start += n
    return np.asarray(rows, dtype=np.int64)


def side_accuracy(x: torch.Tensor, right: torch.Tensor, folds: int = 5, steps: int = 1500) -> float:
    """Cross-validated accuracy of a small classifier (64 units, dropout 0.5) telling the side of the swerve."""
    perm = np.random.default_rng(0).permutation(len(x))
    correct = 0
    for f in range(folds):
        test, train = perm[f::folds], np.setdiff1d(perm, perm[f::folds])
        m, s = x[train].mean(0), x[train].std(0) + 1e-3
        torch.manual_seed(f)
        net = torch.nn.Sequential(
            torch.nn.Linear(x.shape[1], 64), torch.nn.ReLU(), torch.nn.Dropout(0.5), torch.nn.Linear(64, 1)
        )
        opt = torch.optim.AdamW(net.parameters(), lr=1e-3, weight_decay=0.1)
        xt = (x[train] - m) / s
        for _ in range(steps):
            net.train()
            loss = torch.nn.functional.binary_cross_entropy_with_logits(net(xt).squeeze(-1), right[train])
            opt.zero_grad()
            loss.backward()
            opt.step()
        net.eval()
        with torch.no_grad():
            correct += int(((net((x[test] - m) / s).squeeze(-1) > 0).float() == right[test]).sum())
    return correct / len(x)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. experiment=quick demos.episodes=500")
    args = parser.parse_args(argv)
    cfg = compose("train_agent", [*args.overrides, "agent.use_speed=true"])
    set_threads(1)
    encoder = loading.load_world_model(cfg, use_speed=True, frame_view=True)
    action_map = ActionMap("brake", "grip")
    train, _ = imitation.demonstration_buffer(cfg, encoder, action_map, "r2", cfg.agent, "train")
    held, _ = imitation.demonstration_buffer(cfg, encoder, action_map, "r2", cfg.agent, "validation")
    x, y = torch.from_numpy(train.obs[: len(train)]), torch.from_numpy(train.actions[: len(train)])
    xv, yv = torch.from_numpy(held.obs[: len(held)]), torch.from_numpy(held.actions[: len(held)])
    d = encoder.latent_dim
    columns = {  # the encoder's output is [z | zhat | speed | frame view]
        "[z, zhat, speed]": list(range(2 * d + 1)),
        "[z, speed]": list(range(d)) + [2 * d],
        "speed only": [2 * d],
        "[frame view, speed]": list(range(2 * d, x.shape[1])),
        "[z, speed, frame view]": list(range(d)) + list(range(2 * d, x.shape[1])),
        "[z, zhat, speed, frame view]": list(range(x.shape[1])),
    }
    rows = [
        ("zero action (= straight-line braking)", (yv**2).sum(-1).mean().item()),
        ("best constant action", ((y.mean(0) - yv) ** 2).sum(-1).mean().item()),
    ]
    for name, c in columns.items():
        rows.append((name, fit(x[:, c], y, xv[:, c], yv)))
    c = columns["[z, zhat, speed]"]
    for share in (0.25, 0.5):
        n = int(share * len(x))  # the store's order is by episode, so a prefix is whole episodes but the last
        rows.append((f"[z, zhat, speed], {share:g} of the training episodes", fit(x[:n, c], y[:n], xv[:, c], yv)))
    print(f"{len(x)} training and {len(xv)} held-out decisions from {cfg.demos.episodes} demonstrations\n")
    print("| student input | held-out mean squared error |\n|---|---:|")
    for name, value in rows:
        print(f"| {name} | {value:.3f} |")

    # Can the student tell which side the teacher will swerve to, where it first does?
    first = np.concatenate(
        [first_swerves(cfg, y.numpy(), "train"), len(x) + first_swerves(cfg, yv.numpy(), "validation")]
    )
    xa, ya = torch.cat([x, xv])[first], torch.cat([y, yv])[first]
    right = (ya[:, 0] > 0).float()
    print(f"\n{len(first)} episodes swerve, {100 * right.mean().item():.0f} % of them to the right first\n")
    print("| student input | side of the first swerve told right, 5-fold cross-validated |\n|---|---:|")
    if right.min() == right.max():
        print("| (a one-sided teacher: nothing to tell) | 100 % |")
        return 0
    for name in ("[z, speed]", "[frame view, speed]", "[z, zhat, speed, frame view]"):
        print(f"| {name} | {100 * side_accuracy(xa[:, columns[name]], right):.0f} % |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
