"""Phase 2: train the 512-unit LSTM world model on (z_t, a_t) -> z_{t+1}.

    python -m worldmodel.train_rnn experiment=NAME scale=smoke|quick|paper [resume=true]

The dataset is encoded once by the VAE into ``data/NAME/latents.h5`` (re-encoded automatically when the VAE
checkpoint changes). Training sequences are windows of ``rnn.seq_len`` steps, with z resampled from the stored
mu, sigma for every batch (hardmaru's WorldModelsExperiments). Windows start from a zero LSTM state
(truncated back-propagation), as at the start of an episode; episodes shorter than a window are padded and
masked.

Writes ``runs/NAME/rnn/``: checkpoints, TensorBoard (losses and a Fig. 2-style strip per epoch: decoded z_{t-1},
z_t, predicted z_{t+1} and the real next frame), and ``metrics.json`` with held-out next-frame IoU of the decoded
prediction for Vehicles and Pedestrians, beside the persistence baseline (z_{t+1} = z_t).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch

from envs import CLASS_NAMES, NUM_CLASSES
from envs.streams import RNN_OPEN_LOOP_START, RNN_VALIDATION_INPUTS

from . import artifacts, dreams, loading
from .common import StageError, autocast, check_finite, module_device, resolve_device, seed_everything, set_threads
from .config import hydra_main, validate
from .latents import Latents, encode_dataset, is_current
from .training import TrainingRun

log = logging.getLogger(__name__)
LOG_EVERY = 10
VEHICLES, PEDESTRIANS = CLASS_NAMES.index("Vehicles"), CLASS_NAMES.index("Pedestrians")


def ensure_latents(cfg, store, vae, vae_path: Path) -> tuple[Path, bool]:
    """Encode the dataset unless an encoding by this exact VAE checkpoint exists. Returns (path, re-encoded)."""
    path = artifacts.latents_path(cfg)
    if is_current(path, artifacts.file_sha256(vae_path)):
        return path, False
    log.info("[rnn] encoding the dataset with %s -> %s", vae_path, path)
    encode_dataset(store, vae, vae_path, path)
    return path, True


def windows(lengths: dict[int, int], episodes: list[int], seq_len: int) -> list[tuple[int, int, int]]:
    """(episode, start, steps) units covering every transition t -> t+1 once."""
    out = []
    for i in episodes:
        transitions = lengths[i] - 1
        for s in range(0, transitions, seq_len):
            out.append((i, s, min(seq_len, transitions - s)))
    return out


def make_batch(lat: Latents, units, seq_len: int, latent_dim: int, gen: torch.Generator, *, sample_inputs: bool):
    """Inputs z, a (B, L, .), targets z_next and a mask, with z resampled from the stored mu, sigma.

    Targets are always samples. Inputs are samples too when ``sample_inputs`` (World Models), or the means,
    which is what the agent feeds at decision time (z_t = mu(obs_t)).
    """
    B = len(units)
    mu = np.zeros((B, seq_len + 1, latent_dim), np.float32)
    logvar = np.zeros_like(mu)
    act = np.zeros((B, seq_len, 2), np.float32)
    mask = np.zeros((B, seq_len), bool)
    for b, (i, s, n) in enumerate(units):
        m, lv, a = lat.episode(i, slice(s, s + n + 1))
        mu[b, : n + 1], logvar[b, : n + 1], act[b, :n] = m, lv, a[:n]
        mask[b, :n] = True
    mu_t, logvar_t = torch.from_numpy(mu), torch.from_numpy(logvar)
    z = mu_t + torch.exp(0.5 * logvar_t) * torch.randn(mu_t.shape, generator=gen)
    inputs = z[:, :-1] if sample_inputs else mu_t[:, :-1]
    return inputs, torch.from_numpy(act), z[:, 1:], torch.from_numpy(mask)


def masked_loss(model, out: dict, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The head's loss over the valid (unpadded) steps only."""
    if not bool(mask.any()):
        return target.new_zeros(())
    picked = {k: v[mask].unsqueeze(0) for k, v in out.items()}
    return model.loss(picked, target[mask].unsqueeze(0))


def open_loop_loss(model, z, a, z_next, mask, start: int, steps: int) -> torch.Tensor:
    """The loss of ``steps`` predictions made the way the LSTM dreams: teacher-forced on the real ``z`` up to
    ``start``, then fed its own point predictions (gradients flow through them). An action's effect on the frame
    is small in one step and adds up over several, so this is where the loss sees what the action does."""
    if start > 0:
        _, state = model(z[:, :start], a[:, :start])
    else:
        state = model.initial_state(z.shape[0])
    z_in, outs = z[:, start], []
    for j in range(steps):
        out, state = model.step(z_in, a[:, start + j], state)
        outs.append(out)
        z_in = model.predict(out)
    out = {k: torch.stack([o[k] for o in outs], 1) for k in outs[0]}
    return masked_loss(model, out, z_next[:, start : start + steps], mask[:, start : start + steps])


def train_batch(model, opt, batch: tuple, typed, where: tuple[int, int], step: int, checkpoint) -> tuple:
    """One optimiser step on a batch of windows (z, a, z_next, mask); ``where``: (epoch, batch index), which seeds
    the open-loop start. Returns (loss, open-loop loss or None)."""
    hp, (epoch, b) = typed.rnn, where
    z, a, z_next, mask = batch
    dream_loss = None
    with autocast(z.device, typed.amp):
        out, _ = model(z, a)
        loss = masked_loss(model, out, z_next, mask)
        if hp.open_loop_steps:
            starts = np.random.default_rng([typed.seed, epoch, b, RNN_OPEN_LOOP_START])
            start = int(starts.integers(0, hp.seq_len - hp.open_loop_steps + 1))
            dream_loss = open_loop_loss(model, z, a, z_next, mask, start, hp.open_loop_steps)
            loss = loss + hp.open_loop_weight * dream_loss
    check_finite(loss.item(), "LSTM loss", step, checkpoint)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
    opt.step()
    return loss, dream_loss


def log_losses(writer, step: int, loss, dream_loss, opt) -> None:
    writer.add_scalar("loss/train", loss.item(), step)
    if dream_loss is not None:
        writer.add_scalar("loss/train_open_loop", dream_loss.item(), step)
    writer.add_scalar("lr", opt.param_groups[0]["lr"], step)


def log_validation(writer, model, vae, store, lat, episode: int, val_loss: float, step: int) -> None:
    """The validation loss, and Fig. 2's strip of one held-out episode."""
    writer.add_scalar("loss/validation", val_loss, step)
    model.eval()
    writer.add_image(
        "fig2: z_{t-1} | z_t | predicted z_{t+1} | real t+1",
        fig2_strip(model, vae, store, lat, episode),
        step,
        dataformats="HWC",
    )
    model.train()


def final_metrics(cfg, run_, world, device, step: int, best_val: float, reencoded: bool, t0: float) -> dict:
    """The best checkpoint's measurements (metrics.json): next-frame IoU against persistence, and what the LSTM
    dreams (``dreams.measure``), whose action-effect rows are written beside it. ``world``: (vae, store, latents)."""
    hp = validate(cfg).rnn
    vae, store, lat = world
    val_eps = store.episodes("validation") or store.episodes("train")
    model, best_path = loading.load_rnn(cfg, "best")
    model.to(device)  # the measurements run where training did
    scores = prediction_iou(model, vae, store, lat, val_eps)
    effect_rows: list[dict] = []
    validation = store.episodes("validation", branches=False)
    scores.update(dreams.measure(cfg, vae, model, store, lat, validation, run_.writer, rows=effect_rows))
    lat.close()
    if effect_rows:  # the points behind the action effect, for reports that commit them
        dreams.write_effect_rows(effect_rows, run_.dir / "action_effect.rows.csv.gz")
    metrics = {
        "checkpoint": str(best_path),
        "epochs": hp.epochs,
        "steps": step,
        "head": hp.head,
        "validation_loss": best_val,
        "reencoded_latents": reencoded,
        **scores,
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    m, p = scores["model"], scores["persistence"]
    for cls in ("vehicles_iou", "pedestrians_iou"):
        if m[cls] is not None and p[cls] is not None:
            metrics[f"{cls}_gain_over_persistence"] = m[cls] - p[cls]
    log.info(
        "[rnn] next-frame IoU vehicles %s (persistence %s), pedestrians %s (persistence %s); wrote %s",
        m["vehicles_iou"],
        p["vehicles_iou"],
        m["pedestrians_iou"],
        p["pedestrians_iou"],
        run_.marker,
    )
    return metrics


@torch.inference_mode()
def prediction_iou(rnn, vae, store, lat: Latents, episodes: list[int], max_frames: int = 3000) -> dict:
    """Held-out next-frame IoU of decoded predictions, persistence (z_{t+1} = z_t) and reconstruction.

    Targets are the real next segmentation frames, not VAE reconstructions, so the VAE's own error is in every
    number; the reconstruction row is the ceiling a perfect latent prediction could reach.
    """
    from .models.vae import confusion, iou_from_confusion

    conf = {k: np.zeros((NUM_CLASSES, NUM_CLASSES), np.int64) for k in ("model", "persistence", "reconstruction")}
    sq_err = {"model": 0.0, "persistence": 0.0}
    n = 0
    device = module_device(rnn)
    for i in episodes:
        mu, _, act = lat.episode(i)
        if len(mu) < 2:
            continue
        z = torch.from_numpy(mu).unsqueeze(0).to(device)
        a = torch.from_numpy(act).unsqueeze(0).to(device)
        out, _ = rnn(z[:, :-1], a[:, :-1])
        zhat = rnn.predict(out)[0]
        target = torch.from_numpy(store.read(i, "seg")[1:])
        for name, latent in (("model", zhat), ("persistence", z[0, :-1]), ("reconstruction", z[0, 1:])):
            conf[name] += confusion(_decode_classes(vae, latent), target, NUM_CLASSES)
        sq_err["model"] += float(((zhat - z[0, 1:]) ** 2).sum())
        sq_err["persistence"] += float(((z[0, :-1] - z[0, 1:]) ** 2).sum())
        n += len(target)
        if n >= max_frames:
            break
    result = {"frames": n}
    for name, c in conf.items():
        iou = iou_from_confusion(c)
        result[name] = {
            "vehicles_iou": _num(iou[VEHICLES]),
            "pedestrians_iou": _num(iou[PEDESTRIANS]),
            "mean_iou": _num(np.nanmean(iou)),
            "pixel_accuracy": float(np.trace(c) / max(c.sum(), 1)),
        }
    for name, e in sq_err.items():
        result[name]["latent_mse"] = e / max(n, 1) / lat.f.attrs["latent_dim"]
    return result


def _decode_classes(vae, z: torch.Tensor, chunk: int = 64) -> torch.Tensor:
    """Class maps of ``z`` decoded in zero-padded chunks of one size: oneDNN keeps ~9 MB of primitives per input
    shape, and decoding each episode whole (one shape per episode length) grew this stage by gigabytes."""
    n = len(z)
    padded = torch.zeros((-(-n // chunk) * chunk, z.shape[1]), dtype=z.dtype, device=z.device)
    padded[:n] = z
    return torch.cat([vae.decode(part).argmax(1) for part in padded.split(chunk)])[:n].cpu()


def _num(x) -> float | None:
    return None if x is None or np.isnan(x) else float(x)


@torch.inference_mode()
def fig2_strip(rnn, vae, store, lat: Latents, episode: int, times=(4, 8, 12)) -> np.ndarray:
    """Rows of [decoded z_{t-1} | decoded z_t | decoded predicted z_{t+1} | real frame t+1] (paper Fig. 2)."""
    from envs import PALETTE

    mu, _, act = lat.episode(episode)
    T = len(mu)
    device = module_device(rnn)
    out, _ = rnn(torch.from_numpy(mu[:-1]).unsqueeze(0).to(device), torch.from_numpy(act[:-1]).unsqueeze(0).to(device))
    zhat = rnn.predict(out)[0]
    seg = store.read(episode, "seg")
    rows = []
    for t in times:
        t = min(max(1, t), T - 2)
        if t < 1:
            continue
        pair = torch.from_numpy(mu[t - 1 : t + 1]).to(device)
        dec = vae.decode(torch.stack([pair[0], pair[1], zhat[t]])).argmax(1)
        panels = [PALETTE[d] for d in dec.cpu().numpy()] + [PALETTE[seg[t + 1]]]
        rows.append(np.concatenate(panels, axis=1))
    if not rows:
        return np.zeros((64, 256, 3), np.uint8)
    return np.concatenate(rows, axis=0)


def run(cfg) -> dict:
    typed = validate(cfg)
    hp, seed = typed.rnn, typed.seed
    set_threads(typed.threads)
    vae, vae_path = loading.load_vae(cfg, "best")
    store = loading.open_rollouts(cfg)
    seed_everything(seed)
    device = resolve_device(typed.device)
    # built on the CPU first: the same initial weights on every device
    model = loading.build_rnn(cfg.vae, cfg.rnn).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=hp.lr)
    L, D, B = hp.seq_len, typed.vae.latent_dim, hp.batch_size
    sample_inputs = hp.sample_inputs
    train_eps = store.episodes("train")
    val_eps = store.episodes("validation") or train_eps
    train_units = windows(store.lengths, train_eps, L)
    val_units = windows(store.lengths, val_eps, L)
    epochs = hp.epochs

    with TrainingRun(cfg, "train_rnn", artifacts.rnn_dir(cfg), artifacts.provenance(cfg, "rnn")) as run_:
        # after the run's checks: a refused resume must not cost an encoding
        lat_path, reencoded = ensure_latents(cfg, store, vae.to(device), vae_path)
        lat = Latents(lat_path)
        if int(lat.f.attrs["latent_dim"]) != D:
            raise StageError(
                f"{lat_path} has latent size {lat.f.attrs['latent_dim']} but vae.latent_dim={D}; delete it to re-encode"
            )
        if run_.state is not None:
            loading.check_rnn_architecture(run_.state, cfg.vae, cfg.rnn, run_.last)
        epoch, batch_in_epoch, step, best_val = run_.restore(model, opt)

        # what a resume or a loader checks the architecture against
        arch = {"latent_dim": D, "hidden": hp.hidden, "head": hp.head, "residual": hp.residual}

        def snapshot(best: bool = False):
            run_.save_epochs(model, opt, (epoch, batch_in_epoch, step, best_val), best=best, **arch)

        from tqdm import tqdm

        writer = run_.writer
        t0 = time.perf_counter()
        while epoch < epochs:
            rng = np.random.default_rng([seed, epoch])
            gen = torch.Generator().manual_seed(seed * 1000 + epoch)
            order = rng.permutation(len(train_units))
            n_batches = (len(order) + B - 1) // B
            bar = tqdm(total=n_batches, initial=batch_in_epoch, desc=f"rnn epoch {epoch + 1}/{epochs}", unit="batch")
            for b in range(n_batches):
                units = [train_units[u] for u in order[b * B : (b + 1) * B]]
                # drawn even when skipped, so a resumed epoch sees the same noise
                z, a, z_next, mask = make_batch(lat, units, L, D, gen, sample_inputs=sample_inputs)
                if b < batch_in_epoch:
                    continue
                batch = tuple(t.to(device, non_blocking=True) for t in (z, a, z_next, mask))
                loss, dream_loss = train_batch(model, opt, batch, typed, (epoch, b), step, run_.last)
                step += 1
                batch_in_epoch = b + 1
                bar.update(1)
                if step % LOG_EVERY == 0:
                    log_losses(writer, step, loss, dream_loss, opt)
                if run_.stop.requested:
                    break
            bar.close()
            if run_.stop.requested:
                snapshot()
                lat.close()
                return run_.stopped(step)
            val_loss = validation_loss(model, lat, val_units, L, D, B, seed, sample_inputs=sample_inputs)
            log_validation(writer, model, vae, store, lat, val_eps[0], val_loss, step)
            epoch += 1
            batch_in_epoch = 0
            improved = val_loss < best_val
            best_val = min(best_val, val_loss)
            snapshot(best=improved)
            log.info("[rnn] epoch %d: validation loss %.4f", epoch, val_loss)

        metrics = final_metrics(cfg, run_, (vae, store, lat), device, step, best_val, reencoded, t0)
        return run_.finish(metrics)


@torch.inference_mode()
def validation_loss(model, lat, units, L, D, B, seed, *, sample_inputs: bool) -> float:
    """Mean per-step loss over the held-out windows, with the inputs drawn as in training (``rnn.sample_inputs``),
    so ``best.pt`` is chosen on the distribution it was trained on."""
    model.eval()
    device = next(model.parameters()).device
    gen = torch.Generator().manual_seed(seed + RNN_VALIDATION_INPUTS)  # drawn on the CPU: the same on every device
    total, count = 0.0, 0
    for b in range(0, len(units), B):
        batch = make_batch(lat, units[b : b + B], L, D, gen, sample_inputs=sample_inputs)
        z, a, z_next, mask = (t.to(device) for t in batch)
        out, _ = model(z, a)
        total += masked_loss(model, out, z_next, mask).item() * int(mask.sum())
        count += int(mask.sum())
    model.train()
    return total / max(count, 1)


main = hydra_main("train_rnn")(run)

if __name__ == "__main__":
    main()
