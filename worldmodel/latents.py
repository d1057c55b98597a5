"""The dataset encoded once by the VAE: per-frame mu and log sigma^2, reused by every LSTM run.

``data/NAME/latents.h5`` holds one group per episode (``mu``, ``logvar`` ``(T, latent) float32``, ``action``
``(T, 2)``) and the file attributes ``vae_checkpoint`` and ``vae_sha256``: the checkpoint that produced it. When
the VAE checkpoint changes (a retrain, a resume with more epochs), the hash no longer matches and the dataset is
re-encoded automatically; otherwise it is reused as is. Written to a temporary name and renamed when complete
(``common.atomic_output``); a temporary file left by a killed encoder is removed before the next encoding.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import torch

from .artifacts import file_sha256
from .common import atomic_output, clean_temporaries
from .data import RolloutStore, episode_key


def is_current(path: Path, vae_sha: str) -> bool:
    if not path.exists():
        return False
    try:
        with h5py.File(path, "r") as f:
            return f.attrs.get("vae_sha256") == vae_sha
    except OSError:
        return False


@torch.inference_mode()
def encode_dataset(
    store: RolloutStore, vae, vae_path: Path, out: Path, batch_size: int = 256, progress: bool = True
) -> None:
    """Encode every episode of ``store`` with ``vae`` into ``out`` (atomically).

    Frames stream through the encoder in batches of exactly ``batch_size`` across episode boundaries (the last
    batch is padded). oneDNN caches primitives per input shape, ~9 MB each: encoding episode by episode, with
    a different tail shape for nearly every episode length, grew the stage past 5 GB at paper scale.
    """
    from tqdm import tqdm

    vae.eval()
    frames = None  # the fixed-size input batch, allocated once the frame size is known
    fill = 0
    encoded_mu, encoded_logvar = [], []  # encoded frames not yet written, in episode order
    waiting: list[int] = []  # episodes whose frames are queued or encoded but not written

    device = next(vae.parameters()).device

    def encode_batch(valid: int) -> None:
        mu, logvar = vae.encode(torch.from_numpy(frames).to(device))
        encoded_mu.append(mu[:valid].cpu().numpy().astype(np.float32))
        encoded_logvar.append(logvar[:valid].cpu().numpy().astype(np.float32))

    def write_finished(f) -> None:
        mu, logvar = np.concatenate(encoded_mu), np.concatenate(encoded_logvar)
        used = 0
        while waiting and used + store.lengths[waiting[0]] <= len(mu):
            i = waiting.pop(0)
            n = store.lengths[i]
            g = f.create_group(episode_key(i))
            g.create_dataset("mu", data=mu[used : used + n])
            g.create_dataset("logvar", data=logvar[used : used + n])
            g.create_dataset("action", data=store.read(i, "action").astype(np.float32))
            used += n
        encoded_mu[:], encoded_logvar[:] = [mu[used:]], [logvar[used:]]

    clean_temporaries(out.parent, out.name)  # a killed encoder's leftover (this stage is the file's one writer)
    with atomic_output(out) as tmp:
        with h5py.File(tmp, "w") as f:
            f.attrs["vae_checkpoint"] = str(vae_path)
            f.attrs["vae_sha256"] = file_sha256(vae_path)
            f.attrs["latent_dim"] = vae.latent_dim
            for i in tqdm(sorted(store.location), desc="encode", unit="episode", disable=not progress):
                seg = store.read(i, "seg")
                if frames is None:
                    frames = np.zeros((batch_size, *seg.shape[1:]), seg.dtype)
                waiting.append(i)
                pos = 0
                while pos < len(seg):
                    take = min(batch_size - fill, len(seg) - pos)
                    frames[fill : fill + take] = seg[pos : pos + take]
                    fill, pos = fill + take, pos + take
                    if fill == batch_size:
                        encode_batch(batch_size)
                        fill = 0
                        write_finished(f)
            if fill:
                encode_batch(fill)  # the stale tail of the buffer is encoded and dropped
            if waiting:
                write_finished(f)


class Latents:
    """Read access to ``latents.h5`` (one handle, opened lazily)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self._f = None

    @property
    def f(self) -> h5py.File:
        if self._f is None:
            self._f = h5py.File(self.path, "r")
        return self._f

    def episode(self, i: int, sl=slice(None)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        g = self.f[episode_key(i)]
        return g["mu"][sl], g["logvar"][sl], g["action"][sl]

    def length(self, i: int) -> int:
        return self.f[episode_key(i)]["mu"].shape[0]

    def close(self) -> None:
        if self._f is not None:
            self._f.close()
            self._f = None
