"""The dataset encoded once by the VAE: per-frame mu and log sigma^2, reused by every LSTM run.

``data/NAME/latents.h5`` holds one group per episode (``mu``, ``logvar`` ``(T, latent) float32``, ``action``
``(T, 2)``) and the file attributes ``vae_checkpoint`` and ``vae_sha256``: the checkpoint that produced it. When
the VAE checkpoint changes (a retrain, a resume with more epochs), the hash no longer matches and the dataset is
re-encoded automatically; otherwise it is reused as is. Written to a temporary name and renamed when complete.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

import h5py
import numpy as np
import torch

from .data import RolloutStore, episode_key


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def latents_path(data_root: Path) -> Path:
    return Path(data_root) / "latents.h5"


def is_current(path: Path, vae_sha: str) -> bool:
    if not path.exists():
        return False
    try:
        with h5py.File(path, "r") as f:
            return f.attrs.get("vae_sha256") == vae_sha
    except OSError:
        return False


@torch.inference_mode()
def encode_dataset(store: RolloutStore, vae, vae_path: Path, out: Path, batch_size: int = 256,
                   progress: bool = True) -> None:
    """Encode every episode of ``store`` with ``vae`` into ``out`` (atomically)."""
    from tqdm import tqdm

    vae.eval()
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["vae_checkpoint"] = str(vae_path)
            f.attrs["vae_sha256"] = file_sha256(vae_path)
            f.attrs["latent_dim"] = vae.latent_dim
            episodes = sorted(store.location)
            for i in tqdm(episodes, desc="encode", unit="episode", disable=not progress):
                seg = store.read(i, "seg")
                mus, logvars = [], []
                for s in range(0, len(seg), batch_size):
                    mu, logvar = vae.encode(torch.from_numpy(seg[s: s + batch_size]))
                    mus.append(mu.numpy())
                    logvars.append(logvar.numpy())
                g = f.create_group(episode_key(i))
                g.create_dataset("mu", data=np.concatenate(mus).astype(np.float32))
                g.create_dataset("logvar", data=np.concatenate(logvars).astype(np.float32))
                g.create_dataset("action", data=store.read(i, "action").astype(np.float32))
        os.replace(tmp, out)
    finally:
        if tmp.exists():
            tmp.unlink()


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
