"""Phase 1: train the 128-d segmentation VAE on the collected frames.

    python -m worldmodel.train_vae experiment=NAME scale=smoke|quick|paper [resume=true]

Reads ``data/NAME/rollouts`` (streamed, so memory stays bounded), writes ``runs/NAME/vae/``:
``last.pt``/``best.pt`` checkpoints, TensorBoard events (losses, learning rate, an input-vs-reconstruction
grid per epoch) and ``metrics.json`` (held-out pixel accuracy and per-class IoU for all 13 classes).
"""

from __future__ import annotations

import logging
import time

import numpy as np
import torch

from envs import CLASS_NAMES, NUM_CLASSES

from . import artifacts, loading
from .common import autocast, check_finite, resolve_device, resolve_loader_workers, seed_everything, set_threads
from .config import hydra_main, validate
from .data import RolloutStore, iter_frame_batches, loaded_frame_batches
from .training import TrainingRun

log = logging.getLogger(__name__)
LOG_EVERY = 10


def class_weights(store: RolloutStore, episodes: list[int], exponent: float, frames: int = 4000) -> torch.Tensor | None:
    """Per-class loss weights (frequency ** -exponent, normalised so the average pixel weighs 1).

    ``exponent`` 0 is the plain summed cross-entropy of World Models; 0.5 (inverse square root of frequency)
    lets the ~1 % of pixels that are pedestrians and vehicles shape the latent instead of being averaged away.
    """
    if exponent == 0:
        return None
    counts = np.zeros(NUM_CLASSES)
    seen = 0
    for batch in iter_frame_batches(store, episodes, 256, np.random.default_rng(12345)):
        counts += np.bincount(batch.ravel(), minlength=NUM_CLASSES)
        seen += len(batch)
        if seen >= frames:
            break
    freq = counts / counts.sum()
    w = (freq + 1e-4) ** -float(exponent)
    w /= (freq * w).sum()
    return torch.tensor(w, dtype=torch.float32)


def palette_grid(inputs: np.ndarray, recons: np.ndarray) -> np.ndarray:
    """Rows: input frames over their reconstructions, coloured with the class palette (H, W, 3 uint8)."""
    from envs import PALETTE

    top = np.concatenate(list(PALETTE[inputs]), axis=1)
    bottom = np.concatenate(list(PALETTE[recons]), axis=1)
    return np.concatenate([top, bottom], axis=0)


@torch.inference_mode()
def evaluate(model, store: RolloutStore, episodes: list[int], batch_size: int, max_frames: int | None = None) -> dict:
    from .models.vae import confusion, iou_from_confusion, vae_loss

    model.eval()
    device = next(model.parameters()).device
    conf = np.zeros((NUM_CLASSES, NUM_CLASSES), dtype=np.int64)
    recon_sum = kl_sum = 0.0
    n = 0
    for batch in iter_frame_batches(store, episodes, batch_size, np.random.default_rng(0)):
        x = torch.from_numpy(batch).to(device)
        logits, mu, logvar = model(x, sample=False)
        _, recon, kl = vae_loss(logits, x, mu, logvar)
        recon_sum += float(recon) * len(x)
        kl_sum += float(kl) * len(x)
        conf += confusion(logits.argmax(1), x, NUM_CLASSES)
        n += len(x)
        if max_frames and n >= max_frames:
            break
    model.train()
    iou = iou_from_confusion(conf)
    return {
        "frames": n,
        "recon": recon_sum / max(n, 1),
        "kl": kl_sum / max(n, 1),
        "pixel_accuracy": float(np.trace(conf) / max(conf.sum(), 1)),
        "iou": iou,
    }


def frame_batches(store: RolloutStore, episodes: list[int], batch_size: int, rng, workers: int, device):
    """The training batches of one epoch as uint8 tensors: read in this process (``workers`` 0), or by loader
    workers into pinned memory on CUDA; the same frames in the same order either way."""
    if workers == 0:
        return (torch.from_numpy(batch) for batch in iter_frame_batches(store, episodes, batch_size, rng))
    return loaded_frame_batches(store, episodes, batch_size, rng, workers, pin_memory=device.type == "cuda")


def run(cfg) -> dict:

    typed = validate(cfg)
    set_threads(typed.threads)
    store = loading.open_rollouts(cfg)
    out = artifacts.vae_dir(cfg)
    seed_everything(typed.seed)
    device = resolve_device(typed.device)
    loader_workers = resolve_loader_workers(typed.loader_workers, device)
    model = loading.build_vae(cfg.vae).to(device)  # built on the CPU first: the same initial weights on every device
    opt = torch.optim.Adam(model.parameters(), lr=typed.vae.lr)
    epochs, batch_size = typed.vae.epochs, typed.vae.batch_size
    train_eps, val_eps = store.episodes("train"), store.episodes("validation") or store.episodes("train")
    per_epoch = sum(-(-store.lengths[i] // batch_size) for i in train_eps)  # upper bound for the bar

    with TrainingRun(cfg, "train_vae", out, artifacts.provenance(cfg, "vae")) as run_:
        if run_.state is None:
            weights = class_weights(store, train_eps, typed.vae.class_balance)
        else:
            loading.check_vae_architecture(run_.state, cfg.vae, run_.last)
            weights = run_.state.get("class_weights")
        epoch, batch_in_epoch, step, best_val = run_.restore(model, opt)
        weights_here = None if weights is None else weights.to(device)

        # what a resume or a loader checks the architecture against, and the loss weights to resume with
        arch = {
            "latent_dim": typed.vae.latent_dim,
            "channels": typed.vae.channels,
            "num_classes": typed.vae.num_classes,
            "class_weights": weights,
        }

        def snapshot(best: bool = False):
            run_.save_epochs(model, opt, (epoch, batch_in_epoch, step, best_val), best=best, **arch)

        from tqdm import tqdm

        writer = run_.writer
        t0, frames_seen = time.perf_counter(), 0
        while epoch < epochs:
            rng = np.random.default_rng([typed.seed, epoch])
            bar = tqdm(total=per_epoch, initial=batch_in_epoch, desc=f"vae epoch {epoch + 1}/{epochs}", unit="batch")
            for b, batch in enumerate(frame_batches(store, train_eps, batch_size, rng, loader_workers, device)):
                if b < batch_in_epoch:  # resuming mid-epoch: skip what was already trained on
                    continue
                x = batch.to(device, non_blocking=True)
                loss, recon, kl = train_batch(model, opt, x, weights_here, typed, step, run_.last)
                step += 1
                batch_in_epoch = b + 1
                frames_seen += len(x)
                bar.update(1)
                if step % LOG_EVERY == 0:
                    rate = frames_seen / (time.perf_counter() - t0)
                    log_losses(writer, step, {"total": loss, "recon": recon, "kl": kl}, opt, rate)
                if run_.stop.requested:
                    break
            bar.total = bar.n  # the batch count was an upper bound; end the bar at 100 %
            bar.close()
            if run_.stop.requested:
                snapshot()
                return run_.stopped(step)
            val = evaluate(model, store, val_eps, 64)
            log_validation(writer, model, store, val_eps[0], val, step)
            epoch += 1
            batch_in_epoch = 0
            improved = val["recon"] + val["kl"] < best_val
            best_val = min(best_val, val["recon"] + val["kl"])
            snapshot(best=improved)
            log.info(
                "[vae] epoch %d: val recon %.1f kl %.1f pixel acc %.4f",
                epoch,
                val["recon"],
                val["kl"],
                val["pixel_accuracy"],
            )

        return run_.finish(final_metrics(cfg, store, val_eps, device, step, t0, frames_seen))


def train_batch(model, opt, x, class_weights, typed, step: int, checkpoint) -> tuple:
    """One optimiser step on the frames ``x``: (loss, reconstruction, KL)."""
    from .models.vae import vae_loss

    with autocast(x.device, typed.amp):
        logits, mu, logvar = model(x)
        loss, recon, kl = vae_loss(
            logits, x, mu, logvar, typed.vae.kl_weight, typed.vae.free_bits, class_weights=class_weights
        )
    check_finite(loss.item(), "VAE loss", step, checkpoint)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return loss, recon, kl


def log_losses(writer, step: int, losses: dict, opt, frames_per_s: float) -> None:
    for name, value in losses.items():
        writer.add_scalar(f"loss/{name}", value.item(), step)
    writer.add_scalar("lr", opt.param_groups[0]["lr"], step)
    writer.add_scalar("speed/frames_per_s", frames_per_s, step)


def final_metrics(cfg, store: RolloutStore, val_eps, device, step: int, t0: float, frames_seen: int) -> dict:
    """The best checkpoint's held-out figures (metrics.json), and the training's frame rate since ``t0``."""
    typed = validate(cfg)
    out = artifacts.vae_dir(cfg)
    model, best_path = loading.load_vae(cfg, "best")
    final = evaluate(model.to(device), store, val_eps, 64)
    wall = time.perf_counter() - t0
    metrics = {
        "checkpoint": str(best_path),
        "epochs": typed.vae.epochs,
        "steps": step,
        "heldout_frames": final["frames"],
        "pixel_accuracy": final["pixel_accuracy"],
        "recon_nll": final["recon"],
        "kl": final["kl"],
        "iou": {name: (None if np.isnan(v) else float(v)) for name, v in zip(CLASS_NAMES, final["iou"])},
        "train_frames_per_s": round(frames_seen / wall, 1) if frames_seen else None,
    }
    log.info(
        "[vae] held-out pixel accuracy %.4f; IoU Vehicles %s, Pedestrians %s; wrote %s",
        metrics["pixel_accuracy"],
        metrics["iou"]["Vehicles"],
        metrics["iou"]["Pedestrians"],
        out / "metrics.json",
    )
    return metrics


def log_validation(writer, model, store: RolloutStore, episode: int, val: dict, step: int) -> None:
    """Validation scalars and an input-vs-reconstruction grid of one held-out episode."""
    writer.add_scalar("val/recon", val["recon"], step)
    writer.add_scalar("val/kl", val["kl"], step)
    writer.add_scalar("val/pixel_accuracy", val["pixel_accuracy"], step)
    sample = np.stack(
        [store.read(episode, "seg", slice(k, k + 1))[0] for k in range(0, min(store.lengths[episode], 64), 8)]
    )
    with torch.inference_mode():
        device = next(model.parameters()).device
        recon_frames = model.eval().reconstruct(torch.from_numpy(sample).to(device)).cpu().numpy()
    model.train()
    writer.add_image(
        "reconstruction (top: input, bottom: VAE)", palette_grid(sample, recon_frames), step, dataformats="HWC"
    )


main = hydra_main("train_vae")(run)

if __name__ == "__main__":
    main()
