"""What the world model dreams: does the LSTM's imagined future depend on the action, and how far ahead is it right?

Two measurements (docs/design.md §5), written by the LSTM stage into ``runs/NAME/rnn/metrics.json`` and TensorBoard,
and drawn by the notebook:

* ``action_effect``. The simulator's snapshots are the ground truth. In held-out scenarios (their own seed
  stream, never collected), the autopilot drives ``warmup`` steps; the env is snapshotted and rolled ``horizon``
  real steps under each of :data:`ACTIONS` from the same state. The *real* effect of an action at +k is the share
  of pixels where its branch differs from the "keep going" branch (overall, and per class: pixels where exactly
  one of the two frames shows the class). The *dreamt* effect is the same between the decoded open-loop dreams
  of the LSTM, warmed up on the real context and started from the branch point's latent. Their ratio, dreamt
  over real, is how much of what the car's action does the world model knows. The real branches and the metric
  are ``worldmodel/action_effect.py``; this module dreams the branches and measures.
* ``horizon``. Open-loop prediction under the real actions from start points of held-out episodes, scored
  against the real frames k steps ahead, beside persistence, persistence through the VAE and the VAE ceiling.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import torch

from envs import CLASS_NAMES, NUM_CLASSES, PALETTE

# the metric itself, all of which the notebook and the tests also read through this module
from .action_effect import (  # noqa: F401
    ACTIONS,
    DIRECTION_KEYS,
    EFFECT_CLASSES,
    EFFECT_KEYS,
    action_effect,
    branch_bank,
    branch_differences,
    effect_at,
    effect_headline_markdown,
    effect_markdown,
    effect_rows,
    read_effect_rows,
    summarise_effect,
    write_effect_rows,
)
from .common import module_device

HORIZON_KEYS = ("lstm", "persistence", "persistence_vae", "ceiling")
VEHICLES, PEDESTRIANS = CLASS_NAMES.index("Vehicles"), CLASS_NAMES.index("Pedestrians")
log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- dreams
@torch.inference_mode()
def decode_classes(vae, z: torch.Tensor, chunk: int = 64) -> np.ndarray:
    """Latents ``(..., D)`` -> class maps ``(..., H, W)`` uint8, in zero-padded chunks of one size (oneDNN keeps
    primitives per input shape). Decoded on the VAE's device."""
    flat = z.reshape(-1, z.shape[-1]).float().to(module_device(vae))
    n = len(flat)
    padded = torch.zeros((-(-n // chunk) * chunk, flat.shape[1]), dtype=flat.dtype, device=flat.device)
    padded[:n] = flat
    maps = torch.cat([vae.decode(part).argmax(1).to(torch.uint8) for part in padded.split(chunk)])[:n]
    return maps.reshape(*z.shape[:-1], *maps.shape[1:]).cpu().numpy()


@torch.inference_mode()
def imagine(rnn, z0: torch.Tensor, state, actions: torch.Tensor) -> torch.Tensor:
    """Open loop from ``z0 (B, D)`` and ``state``, feeding the LSTM its own point predictions: ``actions (B, K, 2)``
    -> latents ``(B, K, D)``, where ``[:, k]`` predicts the latent k + 1 steps after ``z0``."""
    z, dreamt = z0, []
    for k in range(actions.shape[1]):
        out, state = rnn.step(z, actions[:, k], state)
        z = rnn.predict(out)
        dreamt.append(z)
    return torch.stack(dreamt, 1)


@torch.inference_mode()
def dream_branches(vae, rnn, bank: dict) -> np.ndarray:
    """Decoded dreams ``(N, A, horizon, H, W)`` under :data:`ACTIONS`, from each branch point of ``bank``: the
    LSTM reads the real context (z, a) and then dreams from the branch point's latent. Both models on one device."""
    device = module_device(rnn)
    ctx = torch.from_numpy(bank["context_seg"]).to(device)
    N, C1 = ctx.shape[:2]
    mu, _ = vae.encode(ctx.reshape(N * C1, *ctx.shape[2:]))
    mu = mu.reshape(N, C1, -1)
    _, state = rnn(mu[:, :-1], torch.from_numpy(bank["context_action"]).to(device))
    A, K = bank["seg"].shape[1:3]
    state = tuple(s.repeat_interleave(A, 0) for s in state)
    plans = torch.tensor(list(ACTIONS.values()), dtype=torch.float32, device=device)[None, :, None].expand(N, A, K, 2)
    z = imagine(rnn, mu[:, -1].repeat_interleave(A, 0), state, plans.reshape(N * A, K, 2))
    return decode_classes(vae, z).reshape(N, A, K, *bank["seg"].shape[3:])


@torch.inference_mode()
def reconstruct_classes(vae, seg: np.ndarray, chunk: int = 64) -> np.ndarray:
    """The VAE's reconstruction (encode to the mean latent, decode) of class maps ``(..., H, W)``, in zero-padded
    chunks of one size: the best a dream decoded by this VAE could show."""
    flat = torch.from_numpy(np.ascontiguousarray(seg.reshape(-1, *seg.shape[-2:]))).to(module_device(vae))
    n = len(flat)
    padded = torch.zeros((-(-n // chunk) * chunk, *flat.shape[1:]), dtype=flat.dtype, device=flat.device)
    padded[:n] = flat
    mu = torch.cat([vae.encode(part)[0] for part in padded.split(chunk)])[:n]
    return decode_classes(vae, mu, chunk).reshape(seg.shape)


def measure_action_effect(
    cfg, vae, rnn, points: int, horizon: int = 10, warmup: int = 8, boot: int = 2000, *, seed: int
) -> tuple[dict, dict, np.ndarray, list[dict]]:
    """The branch bank for ``cfg`` (camera env, the collection's autopilot) drawn from ``seed`` (the experiment's),
    the LSTM's dreams, the metric with its intervals, and the per-point rows it is computed from
    (:func:`effect_rows`)."""
    from omegaconf import OmegaConf

    from .common import make_env

    env = make_env(cfg, camera=True)
    try:
        bank = branch_bank(
            env,
            points,
            horizon,
            warmup,
            seed=seed,
            autopilot=OmegaConf.to_container(cfg.collect.autopilot, resolve=True),
        )
    finally:
        env.close()
    dreams = dream_branches(vae, rnn, bank)
    recon = reconstruct_classes(vae, bank["seg"])
    rows = effect_rows(bank["seg"], dreams, bank["valid"], recon, speed=bank["speed"])
    return summarise_effect(rows, horizon, points, boot), bank, dreams, rows


def dream_figure(bank: dict, dreams: np.ndarray, point: int = 0) -> np.ndarray:
    """An RGB strip for TensorBoard: per action, the real branch row above the dreamt one (branch point first)."""
    rows = []
    start = PALETTE[bank["context_seg"][point, -1]]
    for a in range(dreams.shape[1]):
        for frames in (bank["seg"][point, a], dreams[point, a]):
            rows.append(np.concatenate([start, *PALETTE[frames]], axis=1))
        rows.append(np.full((2, rows[-1].shape[1], 3), 255, np.uint8))
    return np.concatenate(rows, axis=0)


# ----------------------------------------------------------------------------- quality against horizon
def _scores(conf: np.ndarray) -> dict[str, float | None]:
    from .models.vae import iou_from_confusion

    iou = iou_from_confusion(conf)
    v, p = iou[VEHICLES], iou[PEDESTRIANS]
    both = [x for x in (v, p) if not np.isnan(x)]

    def num(x):
        return None if x is None or np.isnan(x) else float(x)

    return {
        "pixel_accuracy": float(np.trace(conf) / max(conf.sum(), 1)),
        "vehicles_iou": num(v),
        "pedestrians_iou": num(p),
        "hazard_iou": num(float(np.mean(both)) if both else np.nan),
    }


@torch.inference_mode()
def horizon_quality(vae, rnn, store, lat, episodes: list[int], horizon: int = 10, every: int = 5) -> dict:
    """Open-loop prediction under the real actions, k = 1..horizon steps ahead, against the real frames, beside
    ``persistence`` (the real frame t0 held), ``persistence_vae`` (decode(z_t0) held: the untrained residual
    LSTM) and ``ceiling`` (decode(mu_{t0+k})). A start point counts for the horizons it has frames for."""
    from .models.vae import confusion

    conf = {key: np.zeros((horizon, NUM_CLASSES, NUM_CLASSES), np.int64) for key in HORIZON_KEYS}
    starts_per_k = np.zeros(horizon, int)
    device = module_device(rnn)
    for i in episodes:
        mu_np, _, act_np = lat.episode(i)
        seg = store.read(i, "seg")
        T = len(seg)
        starts = np.arange(0, T - 1, every)
        K = min(horizon, T - 1)
        if len(starts) == 0 or K < 1:
            continue
        mu, act = torch.from_numpy(mu_np).to(device), torch.from_numpy(act_np).to(device)
        # the LSTM state after reading (z_s, a_s) for s < t, at every t
        h, c = rnn.initial_state(1)
        hs, cs = [h], [c]
        for t in range(T - 1):
            _, (h, c) = rnn.step(mu[t : t + 1], act[t : t + 1], (h, c))
            hs.append(h)
            cs.append(c)
        hs, cs = torch.cat(hs), torch.cat(cs)
        steps = np.minimum(starts[:, None] + np.arange(K)[None], T - 1)
        z = imagine(rnn, mu[starts], (hs[starts], cs[starts]), act[steps])
        dreamt = decode_classes(vae, z)
        recon = decode_classes(vae, mu)
        for k in range(1, K + 1):
            ok = starts + k <= T - 1
            if not ok.any():
                break
            s = starts[ok]
            target = seg[s + k]
            for key, frames in (
                ("lstm", dreamt[ok, k - 1]),
                ("persistence", seg[s]),
                ("persistence_vae", recon[s]),
                ("ceiling", recon[s + k]),
            ):
                conf[key][k - 1] += confusion(torch.from_numpy(frames), torch.from_numpy(target), NUM_CLASSES)
            starts_per_k[k - 1] += len(s)
    result: dict = {"horizons": list(range(1, horizon + 1)), "starts": [int(x) for x in starts_per_k]}
    for key in HORIZON_KEYS:
        per_k = [_scores(conf[key][k]) for k in range(horizon)]
        result[key] = {m: [row[m] for row in per_k] for m in per_k[0]}
    return result


def beats_decoded_persistence(result: dict) -> dict[str, bool]:
    """Whether the LSTM is above persistence through the VAE at every horizon, in pixel accuracy and in the mean
    IoU of Vehicles and Pedestrians (a bar of docs/design.md §7)."""
    out = {}
    for metric in ("pixel_accuracy", "hazard_iou"):
        m, p = result["lstm"][metric], result["persistence_vae"][metric]
        out[metric] = all(a is not None and b is not None and a > b for a, b in zip(m, p))
    return out


# ----------------------------------------------------------------------------- both, as the stage runs them
def measure(
    cfg, vae, rnn, store, lat, episodes: list[int], writer=None, step: int = 0, rows: list | None = None
) -> dict:
    """``action_effect`` and ``horizon`` (worldmodel/dreams.py) as ``rnn.effect_*`` and ``rnn.horizon_episodes``
    ask, logged to TensorBoard when ``writer`` is given; the action effect's per-point rows are added to ``rows``."""
    from .config import validate

    typed = validate(cfg)
    rnn_cfg = typed.rnn
    out: dict = {}
    t0 = time.perf_counter()
    if rnn_cfg.effect_points > 0:
        effect, bank, dreamt, effect_rows_ = measure_action_effect(
            cfg, vae, rnn, rnn_cfg.effect_points, rnn_cfg.effect_horizon, seed=typed.seed
        )
        out["action_effect"] = effect
        if rows is not None:
            rows += effect_rows_
        at5 = effect_at(effect, min(5, rnn_cfg.effect_horizon))
        log.info("[dreams] action effect, dreamt / real at +5 steps: %s", {k: _round(v) for k, v in at5.items()})
        if writer is not None:
            for name, entry in effect["actions"].items():
                for h, ratio in zip(effect["horizons"], entry["ratio"]["all"]):
                    if ratio is not None:
                        writer.add_scalar(f"action_effect/{name}_dreamt_over_real", ratio, h)
            writer.add_image(
                "action effect: per action, real branch over dreamt",
                dream_figure(bank, dreamt),
                step,
                dataformats="HWC",
            )
    if rnn_cfg.horizon_episodes > 0 and episodes:
        quality = horizon_quality(vae, rnn, store, lat, episodes[: rnn_cfg.horizon_episodes], rnn_cfg.effect_horizon)
        quality["lstm_beats_decoded_persistence"] = beats_decoded_persistence(quality)
        out["horizon"] = quality
        if writer is not None:
            for key in HORIZON_KEYS:
                for h, acc in zip(quality["horizons"], quality[key]["pixel_accuracy"]):
                    writer.add_scalar(f"horizon_pixel_accuracy/{key}", acc, h)
    out["dreams_wall_s"] = round(time.perf_counter() - t0, 1)
    return out


def _round(x):
    return None if x is None else round(x, 3)


# ----------------------------------------------------------------------------- reports
def markdown(result: dict, horizons=(1, 3, 5, 10)) -> str:
    """The action effect (real, dreamt, ratio per action and class) and quality against horizon as tables."""
    lines = []
    effect = result.get("action_effect")
    if effect:
        lines += effect_markdown(effect, horizons)
    quality = result.get("horizon")
    if quality:
        lines += [
            f"Open-loop quality against horizon under the real actions ({quality['starts'][0]} start points at +1): "
            "pixel accuracy / mean IoU of Vehicles and Pedestrians.",
            "",
            "| k | " + " | ".join(HORIZON_KEYS) + " |",
            "|---:|" + "---:|" * len(HORIZON_KEYS),
        ]
        for i, k in enumerate(quality["horizons"]):
            cells = []
            for key in HORIZON_KEYS:
                acc, iou = quality[key]["pixel_accuracy"][i], quality[key]["hazard_iou"][i]
                cells.append(f"{acc:.3f} / " + ("–" if iou is None else f"{iou:.3f}"))
            lines.append(f"| {k} | " + " | ".join(cells) + " |")
        beats = quality.get("lstm_beats_decoded_persistence") or beats_decoded_persistence(quality)
        lines += ["", f"LSTM above persistence through the VAE at every horizon: {beats}.", ""]
    return "\n".join(lines)


def plot(result: dict, path) -> None:
    """Two panels: the ratio dreamt / real per action against horizon, and pixel accuracy against horizon."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
    effect, quality = result.get("action_effect"), result.get("horizon")
    if effect:
        for name, entry in effect["actions"].items():
            ratio = [np.nan if r is None else r for r in entry["ratio"]["all"]]
            axes[0].plot(effect["horizons"], ratio, marker="o", label=name)
        axes[0].axhline(1.0, color="0.5", ls=":")
        axes[0].axhline(0.5, color="C3", ls="--", lw=0.8)
        axes[0].set_ylim(0, 2)
        axes[0].set_title(f"action effect, dreamt / real ({effect['points']} branch points)", fontsize=10)
        axes[0].set_xlabel("steps after the branch point (1/15 s)")
        axes[0].legend(fontsize=8)
    if quality:
        for ax, metric, label in (
            (axes[1], "pixel_accuracy", "pixel accuracy"),
            (axes[2], "hazard_iou", "mean IoU, Vehicles + Pedestrians"),
        ):
            for key, style in zip(HORIZON_KEYS, ("o-", "s-", "--", ":")):
                values = [np.nan if v is None else v for v in quality[key][metric]]
                ax.plot(quality["horizons"], values, style, label=key)
            ax.set_title(f"open loop, real actions: {label}", fontsize=10)
            ax.set_xlabel("horizon k (steps of 1/15 s)")
        axes[1].legend(fontsize=8)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------- command line
def run(cfg) -> dict:
    """Measure the trained world model of ``experiment=NAME`` again, without training: ``action_effect`` and
    ``horizon`` into ``runs/NAME/rnn/dreams.json`` (the LSTM stage writes the same into its ``metrics.json``), with
    their tables in ``dreams.md`` and a figure in ``dreams.png``.

        python -m worldmodel.dreams experiment=NAME scale=smoke|quick|paper [rnn.effect_points=100]
    """
    import json

    from . import artifacts, loading
    from .common import atomic_write_text, resolve_device, set_threads
    from .config import validate
    from .latents import Latents

    typed = validate(cfg)
    set_threads(typed.threads)
    device = resolve_device(typed.device)
    vae, _ = loading.load_vae(cfg, "best")
    rnn, rnn_path = loading.load_rnn(cfg, "best")
    vae, rnn = vae.to(device), rnn.to(device)
    store = loading.open_rollouts(cfg)
    lat = Latents(artifacts.latents_path(cfg))
    rows: list[dict] = []
    try:
        result = {
            "checkpoint": str(rnn_path),
            **measure(cfg, vae, rnn, store, lat, store.episodes("validation", branches=False), rows=rows),
        }
    finally:
        lat.close()
        store.close()
    out = artifacts.rnn_dir(cfg) / "dreams.json"
    atomic_write_text(out, json.dumps(result, indent=1))
    if rows:
        write_effect_rows(rows, out.with_name("action_effect.rows.csv.gz"))
    atomic_write_text(out.with_suffix(".md"), markdown(result))
    plot(result, out.with_suffix(".png"))
    print(markdown(result))
    print(f"wrote {out} and beside it dreams.md, dreams.png and the action effect's rows, action_effect.rows.csv.gz")
    return result


def _main():
    from .config import hydra_main

    return hydra_main("train_rnn")(run)()


if __name__ == "__main__":
    _main()
