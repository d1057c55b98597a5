"""Phase 1: train the 128-d segmentation VAE on the collected frames.

    python -m worldmodel.train_vae experiment=NAME scale=smoke|quick|paper [resume=true]

Reads ``data/NAME/rollouts`` (streamed, so memory stays bounded), writes ``runs/NAME/vae/``:
``last.pt``/``best.pt`` checkpoints, TensorBoard events (losses, learning rate, an input-vs-reconstruction
grid per epoch) and ``metrics.json`` (held-out pixel accuracy and per-class IoU for all 13 classes).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from .common import (StageError, atomic_write_text, check_finite, data_dir, hydra_main, positive, runs_dir,
                     seed_everything, set_threads, stage_command)
from .data import CorruptDataError, RolloutStore, iter_frame_batches
from .training import Checkpoints, GracefulStop, tensorboard

STAGE = "vae"
LOG_EVERY = 10


def vae_dir(cfg) -> Path:
    return runs_dir(cfg, STAGE)


def open_rollouts(cfg) -> RolloutStore:
    root = data_dir(cfg) / "rollouts"
    if not (root / "manifest.json").exists():
        raise StageError(f"no complete rollout dataset at {root}. Run `{stage_command('collect', cfg)}` first.")
    try:
        return RolloutStore(root)
    except CorruptDataError as err:
        raise StageError(str(err)) from err


def validate_config(cfg) -> None:
    positive(cfg.vae, "latent_dim", "batch_size", "epochs", "lr", where="vae")
    if cfg.vae.num_classes != 13:
        raise StageError(f"config vae.num_classes={cfg.vae.num_classes}: the simulator renders 13 classes")
    if not 0.0 <= cfg.vae.class_balance <= 1.0:
        raise StageError(f"config vae.class_balance={cfg.vae.class_balance} must be in [0, 1]")
    if cfg.vae.free_bits < 0:
        raise StageError(f"config vae.free_bits={cfg.vae.free_bits} must be >= 0")


def build_model(cfg):
    from .models.vae import SegVAE

    return SegVAE(num_classes=int(cfg.vae.num_classes), latent_dim=int(cfg.vae.latent_dim))


def load_vae(cfg, which: str = "best"):
    """The trained VAE of this experiment (eval mode); a clear error if it is missing or does not fit."""
    from .common import load_checkpoint

    path = vae_dir(cfg) / f"{which}.pt"
    state = load_checkpoint(path, "VAE checkpoint", "train_vae", cfg)
    if state["latent_dim"] != cfg.vae.latent_dim:
        raise StageError(f"{path} has latent size {state['latent_dim']} but config vae.latent_dim="
                         f"{cfg.vae.latent_dim}. Set vae.latent_dim={state['latent_dim']} or retrain the VAE.")
    model = build_model(cfg)
    model.load_state_dict(state["model"])
    model.eval()
    return model, path


def class_weights(store: RolloutStore, episodes: list[int], exponent: float, frames: int = 4000) -> torch.Tensor | None:
    """Per-class loss weights (frequency ** -exponent, normalised so the average pixel weighs 1).

    ``exponent`` 0 is the plain summed cross-entropy of World Models; 0.5 (inverse square root of frequency)
    lets the ~1 % of pixels that are pedestrians and vehicles shape the latent instead of being averaged away.
    """
    if exponent == 0:
        return None
    counts = np.zeros(13)
    seen = 0
    for batch in iter_frame_batches(store, episodes, 256, np.random.default_rng(12345)):
        counts += np.bincount(batch.ravel(), minlength=13)
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
    conf = np.zeros((13, 13), dtype=np.int64)
    recon_sum = kl_sum = 0.0
    n = 0
    for batch in iter_frame_batches(store, episodes, batch_size, np.random.default_rng(0)):
        x = torch.from_numpy(batch)
        logits, mu, logvar = model(x, sample=False)
        _, recon, kl = vae_loss(logits, x, mu, logvar)
        recon_sum += float(recon) * len(x)
        kl_sum += float(kl) * len(x)
        conf += confusion(logits.argmax(1), x, 13)
        n += len(x)
        if max_frames and n >= max_frames:
            break
    model.train()
    iou = iou_from_confusion(conf)
    return {"frames": n, "recon": recon_sum / max(n, 1), "kl": kl_sum / max(n, 1),
            "pixel_accuracy": float(np.trace(conf) / max(conf.sum(), 1)), "iou": iou}


def run(cfg) -> dict:
    from envs import CLASS_NAMES

    from .models.vae import vae_loss

    validate_config(cfg)
    set_threads(cfg.threads)
    store = open_rollouts(cfg)
    out = vae_dir(cfg)
    ckpts = Checkpoints(out, "train_vae", cfg)
    if (out / "metrics.json").exists() and not cfg.resume:
        raise StageError(f"{out} holds a finished VAE. Pass resume=true to keep it, or delete {out} to retrain.")

    seed_everything(int(cfg.seed))
    model = build_model(cfg)
    opt = torch.optim.Adam(model.parameters(), lr=float(cfg.vae.lr))
    epoch, batch_in_epoch, step, best_val = 0, 0, 0, float("inf")
    weights = class_weights(store, store.episodes("train"), float(cfg.vae.class_balance))
    state = ckpts.resume_state(bool(cfg.resume))
    if state is not None:
        if state["latent_dim"] != cfg.vae.latent_dim:
            raise StageError(f"{ckpts.last} has latent size {state['latent_dim']}, config says "
                             f"vae.latent_dim={cfg.vae.latent_dim}. Use the same size or delete {out}.")
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        epoch, batch_in_epoch, step, best_val = state["epoch"], state["batch_in_epoch"], state["step"], state["best_val"]
        weights = state.get("class_weights")
        print(f"[vae] resuming from {ckpts.last}: epoch {epoch}, step {step}")

    epochs = int(cfg.vae.epochs)
    train_eps, val_eps = store.episodes("train"), store.episodes("validation") or store.episodes("train")
    batch_size = int(cfg.vae.batch_size)
    per_epoch = sum(-(-store.lengths[i] // batch_size) for i in train_eps)  # upper bound for the bar

    def snapshot(best: bool = False):
        ckpts.save({"model": model.state_dict(), "optimizer": opt.state_dict(), "epoch": epoch,
                    "batch_in_epoch": batch_in_epoch, "step": step, "best_val": best_val,
                    "latent_dim": int(cfg.vae.latent_dim), "num_classes": int(cfg.vae.num_classes),
                    "class_weights": weights}, best=best)

    from tqdm import tqdm

    writer = tensorboard(out, purge_step=step + 1 if state is not None else None)
    t0, frames_seen = time.perf_counter(), 0
    stopped = False
    with GracefulStop() as stop:
        while epoch < epochs and not stopped:
            rng = np.random.default_rng([int(cfg.seed), epoch])
            batches = iter_frame_batches(store, train_eps, batch_size, rng)
            bar = tqdm(total=per_epoch, initial=batch_in_epoch, desc=f"vae epoch {epoch + 1}/{epochs}", unit="batch")
            for b, batch in enumerate(batches):
                if b < batch_in_epoch:          # resuming mid-epoch: skip what was already trained on
                    continue
                x = torch.from_numpy(batch)
                logits, mu, logvar = model(x)
                loss, recon, kl = vae_loss(logits, x, mu, logvar, float(cfg.vae.kl_weight), float(cfg.vae.free_bits),
                                           class_weights=weights)
                check_finite(loss.item(), "VAE loss", step, ckpts.last)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                step += 1
                batch_in_epoch = b + 1
                frames_seen += len(x)
                bar.update(1)
                if step % LOG_EVERY == 0:
                    writer.add_scalar("loss/total", loss.item(), step)
                    writer.add_scalar("loss/recon", recon.item(), step)
                    writer.add_scalar("loss/kl", kl.item(), step)
                    writer.add_scalar("lr", opt.param_groups[0]["lr"], step)
                    writer.add_scalar("speed/frames_per_s", frames_seen / (time.perf_counter() - t0), step)
                if stop.requested:
                    stopped = True
                    break
            bar.total = bar.n   # the batch count was an upper bound; end the bar at 100 %
            bar.close()
            if stopped:
                snapshot()
                print(f"[vae] stopped at step {step}; resume with resume=true")
                break
            val = evaluate(model, store, val_eps, 64)
            writer.add_scalar("val/recon", val["recon"], step)
            writer.add_scalar("val/kl", val["kl"], step)
            writer.add_scalar("val/pixel_accuracy", val["pixel_accuracy"], step)
            sample = np.stack([store.read(val_eps[0], "seg", slice(k, k + 1))[0]
                               for k in range(0, min(store.lengths[val_eps[0]], 64), 8)])
            with torch.inference_mode():
                recon_frames = model.eval().reconstruct(torch.from_numpy(sample)).numpy()
            model.train()
            writer.add_image("reconstruction (top: input, bottom: VAE)", palette_grid(sample, recon_frames), step,
                             dataformats="HWC")
            epoch += 1
            batch_in_epoch = 0
            improved = val["recon"] + val["kl"] < best_val
            best_val = min(best_val, val["recon"] + val["kl"])
            snapshot(best=improved)
            print(f"[vae] epoch {epoch}: val recon {val['recon']:.1f} kl {val['kl']:.1f} "
                  f"pixel acc {val['pixel_accuracy']:.4f}")
    writer.close()
    if stopped:
        return {"stopped": True, "step": step}

    model, best_path = load_vae(cfg, "best")
    final = evaluate(model, store, val_eps, 64)
    wall = time.perf_counter() - t0
    metrics = {
        "checkpoint": str(best_path), "epochs": epochs, "steps": step, "heldout_frames": final["frames"],
        "pixel_accuracy": final["pixel_accuracy"], "recon_nll": final["recon"], "kl": final["kl"],
        "iou": {name: (None if np.isnan(v) else float(v)) for name, v in zip(CLASS_NAMES, final["iou"])},
        "train_frames_per_s": round(frames_seen / wall, 1) if frames_seen else None,
    }
    atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=2))
    print(f"[vae] held-out pixel accuracy {metrics['pixel_accuracy']:.4f}; IoU Vehicles "
          f"{metrics['iou']['Vehicles']}, Pedestrians {metrics['iou']['Pedestrians']}; wrote {out / 'metrics.json'}")
    return metrics


main = hydra_main("train_vae")(run)

if __name__ == "__main__":
    main()
