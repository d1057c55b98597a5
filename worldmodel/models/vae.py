"""World Models convolutional VAE for 64x64 semantic-segmentation class maps.

The VAE sees the scene as a one-hot map of ``num_classes`` semantic classes (Porav & Newman 2018 feed the
segmentation, not RGB, so the latent only has to encode layout: where the road, the cars and the pedestrians
are). Architecture follows Ha & Schmidhuber (2018) exactly, except that the input has ``num_classes``
channels and the decoder emits per-class logits trained with cross-entropy instead of a sigmoid image
trained with MSE.

Also here: the VAE loss (with optional free bits) and the segmentation metrics used to judge
reconstructions (pixel accuracy, confusion matrix, per-class IoU).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from envs.scene import NUM_CLASSES

__all__ = [
    "SegVAE",
    "vae_loss",
    "kl_per_dim",
    "pixel_accuracy",
    "confusion",
    "iou_from_confusion",
    "per_class_iou",
]

IMAGE_SIZE = 64
CHANNELS = 32  # the first conv's channels in World Models' VAE; each later layer's are a multiple of them


class SegVAE(nn.Module):
    """Conv VAE over integer class maps ``(B, 64, 64)`` with values in ``[0, num_classes)``.

    Encoder: 4 conv layers (32, 64, 128, 256 channels, kernel 4, stride 2, ReLU): 64->31->14->6->2,
    flattened to 1024, then linear heads for ``mu`` and ``logvar``.
    Decoder: linear latent->1024 viewed as (1024, 1, 1), then transposed convs 1024->128 (k5), 128->64 (k5),
    64->32 (k6), 32->num_classes (k6), all stride 2: 1->5->13->30->64. Output is LOGITS (no softmax) so the
    loss can use the numerically stable fused log-softmax of ``F.cross_entropy``.

    Those are the sizes at ``channels=32``, World Models' own; ``channels=c`` scales every layer by c / 32 (the
    encoder's c, 2c, 4c, 8c channels, 32c features), as the smoke scale's tests use to keep their checkpoints small.

    The one-hot input is built explicitly with ``F.one_hot``. A fused first layer (an embedding-bag lookup
    of conv weights, numerically identical) was measured and dropped: it halves the cost of ``enc1`` alone
    but gave no measurable end-to-end gain on CPU, and its sort-based backward made training slower.
    The agent's batch-1 decision path does use such a lookup (``worldmodel.models.fast_decision.FastDecision``, built
    from these parameters): there, with no backward and no batch to amortise the one-hot, it pays off.
    """

    def __init__(self, num_classes: int = NUM_CLASSES, latent_dim: int = 128, channels: int = CHANNELS):
        super().__init__()
        if num_classes < 2:
            raise ValueError(f"num_classes must be >= 2, got {num_classes}")
        if latent_dim < 1:
            raise ValueError(f"latent_dim must be >= 1, got {latent_dim}")
        if channels < 1:
            raise ValueError(f"channels must be >= 1, got {channels}")
        self.num_classes = int(num_classes)
        self.latent_dim = int(latent_dim)
        self.channels = c = int(channels)
        self.features = 32 * c  # 8c channels x 2 x 2 after the fourth stride-2 conv on a 64x64 input

        self.enc1 = nn.Conv2d(num_classes, c, 4, stride=2)
        self.enc2 = nn.Conv2d(c, 2 * c, 4, stride=2)
        self.enc3 = nn.Conv2d(2 * c, 4 * c, 4, stride=2)
        self.enc4 = nn.Conv2d(4 * c, 8 * c, 4, stride=2)
        self.fc_mu = nn.Linear(self.features, latent_dim)
        self.fc_logvar = nn.Linear(self.features, latent_dim)

        self.fc_dec = nn.Linear(latent_dim, self.features)
        self.dec1 = nn.ConvTranspose2d(self.features, 4 * c, 5, stride=2)
        self.dec2 = nn.ConvTranspose2d(4 * c, 2 * c, 5, stride=2)
        self.dec3 = nn.ConvTranspose2d(2 * c, c, 6, stride=2)
        self.dec4 = nn.ConvTranspose2d(c, num_classes, 6, stride=2)

    # ------------------------------------------------------------------ input
    def _check_classes(self, seg: torch.Tensor) -> torch.Tensor:
        if seg.dim() != 3 or seg.shape[-2:] != (IMAGE_SIZE, IMAGE_SIZE):
            raise ValueError(
                f"SegVAE expects an integer class map of shape (B, {IMAGE_SIZE}, {IMAGE_SIZE}), got {tuple(seg.shape)}"
            )
        if seg.is_floating_point() or seg.is_complex() or seg.dtype == torch.bool:
            raise ValueError(f"class map must have an integer dtype (uint8/int64), got {seg.dtype}")
        seg = seg.long()
        # An out-of-range id would otherwise surface as an opaque index error deep inside one_hot/embedding.
        if seg.numel() and (int(seg.min()) < 0 or int(seg.max()) >= self.num_classes):
            raise ValueError(
                f"class ids must lie in [0, {self.num_classes}), got range [{int(seg.min())}, {int(seg.max())}]"
            )
        return seg

    def one_hot(self, seg: torch.Tensor) -> torch.Tensor:
        """``(B, 64, 64)`` integer map -> ``(B, C, 64, 64)`` float one-hot (the VAE's nominal input)."""
        seg = self._check_classes(seg)
        return F.one_hot(seg, self.num_classes).permute(0, 3, 1, 2).float()

    # ------------------------------------------------------------------ VAE
    def encode(self, seg: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Integer class map ``(B, 64, 64)`` -> ``(mu, logvar)``, each ``(B, latent_dim)``."""
        h = F.relu(self.enc1(self.one_hot(seg)))
        h = F.relu(self.enc2(h))
        h = F.relu(self.enc3(h))
        h = F.relu(self.enc4(h))
        h = h.flatten(1)
        return self.fc_mu(h), self.fc_logvar(h)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Latent ``(B, latent_dim)`` -> class logits ``(B, num_classes, 64, 64)``."""
        if z.dim() != 2 or z.shape[1] != self.latent_dim:
            raise ValueError(f"decode expects z of shape (B, {self.latent_dim}), got {tuple(z.shape)}")
        h = F.relu(self._dec1_from_vector(self.fc_dec(z)))
        h = F.relu(self.dec2(h))
        h = F.relu(self.dec3(h))
        return self.dec4(h)

    def _dec1_from_vector(self, h: torch.Tensor) -> torch.Tensor:
        """``dec1(h.view(B, 1024, 1, 1))`` computed as one matrix product.

        A transposed conv on a 1x1 input just writes ``h @ W`` into a 5x5 patch, so it is exactly a linear
        layer whose weight is the conv's own ``(1024, 128, 5, 5)`` parameter viewed as ``(1024, 128*25)``.
        The generic CPU transposed-conv kernel is ~20x slower on this shape and dominated VAE training time;
        the parameters (and state_dict) are the ConvTranspose2d's, so checkpoints are unaffected.
        """
        w = self.dec1.weight
        out = torch.mm(h, w.reshape(w.shape[0], -1)).view(h.shape[0], w.shape[1], *w.shape[2:])
        return out + self.dec1.bias.view(1, -1, 1, 1)

    @staticmethod
    def reparameterize(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
        return mu + torch.randn_like(mu) * torch.exp(0.5 * logvar)

    def forward(self, seg: torch.Tensor, sample: bool = True) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Return ``(logits, mu, logvar)``; decodes a reparameterised sample, or ``mu`` if ``sample=False``."""
        mu, logvar = self.encode(seg)
        z = self.reparameterize(mu, logvar) if sample else mu
        return self.decode(z), mu, logvar

    @torch.no_grad()
    def reconstruct(self, seg: torch.Tensor) -> torch.Tensor:
        """Deterministic reconstruction: ``argmax`` of ``decode(mu)`` as a ``(B, 64, 64)`` long class map."""
        mu, _ = self.encode(seg)
        return self.decode(mu).argmax(dim=1)


# ---------------------------------------------------------------------------- loss
def kl_per_dim(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """Batch-mean ``KL(q(z|x) || N(0, I))`` per latent dimension, shape ``(latent_dim,)``.

    Useful for logging how many dimensions are active (KL well above 0) independently of free bits.
    """
    kl = -0.5 * (1.0 + logvar - mu.pow(2) - logvar.exp())
    return kl.mean(dim=0)


def vae_loss(
    logits: torch.Tensor,
    target: torch.Tensor,
    mu: torch.Tensor,
    logvar: torch.Tensor,
    kl_weight: float = 1.0,
    free_bits: float = 0.0,
    class_weights: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Return ``(total, recon, kl)`` with ``total = recon + kl_weight * kl``.

    ``recon``: per-pixel cross-entropy SUMMED over the 64x64 pixels, averaged over the batch, i.e. the
    negative log-likelihood of the whole map; summing (not averaging) pixels keeps the reconstruction and KL
    terms on the ELBO's relative scale, so ``kl_weight=1`` is the true beta=1 VAE.

    ``kl``: ``KL(q || N(0, I))`` summed over latent dimensions, averaged over the batch. With
    ``free_bits > 0`` each dimension's batch-mean KL is clamped below at ``free_bits`` nats
    (Kingma et al. 2016), so dimensions under the budget get no gradient pushing them to the prior. The
    returned ``kl`` is the clamped value actually penalised (so the identity above always holds); use
    :func:`kl_per_dim` for the raw rate.

    ``class_weights`` (C,) reweights each pixel's cross-entropy by its true class, so that small but
    decisive classes (pedestrians, vehicles: ~1 % of pixels) are not drowned by road and sky.
    """
    if logits.dim() != 4 or target.shape != (logits.shape[0], *logits.shape[2:]):
        raise ValueError(
            f"logits must be (B, C, H, W) and target (B, H, W); got {tuple(logits.shape)} and {tuple(target.shape)}"
        )
    if free_bits < 0:
        raise ValueError(f"free_bits must be >= 0, got {free_bits}")
    batch = logits.shape[0]
    recon = F.cross_entropy(logits, target.long(), weight=class_weights, reduction="sum") / batch
    per_dim = kl_per_dim(mu, logvar)
    if free_bits > 0:
        per_dim = per_dim.clamp(min=free_bits)
    kl = per_dim.sum()
    return recon + kl_weight * kl, recon, kl


# ---------------------------------------------------------------------------- metrics
def _as_numpy_int(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x).astype(np.int64, copy=False)


def pixel_accuracy(pred, target) -> float:
    """Share of pixels whose predicted class equals the target class (torch tensors or numpy arrays)."""
    p, t = _as_numpy_int(pred), _as_numpy_int(target)
    if p.shape != t.shape:
        raise ValueError(f"pred and target shapes differ: {p.shape} vs {t.shape}")
    if p.size == 0:
        raise ValueError("pixel_accuracy of an empty array is undefined")
    return float((p == t).mean())


def confusion(pred, target, num_classes: int) -> np.ndarray:
    """``(C, C)`` int64 confusion matrix: ``conf[true, predicted]`` pixel counts.

    Confusion matrices add, so summing them over batches and calling :func:`iou_from_confusion` once gives
    dataset-level IoU (not the biased mean of per-batch IoUs).
    """
    p, t = _as_numpy_int(pred).ravel(), _as_numpy_int(target).ravel()
    if p.shape != t.shape:
        raise ValueError(f"pred and target sizes differ: {p.size} vs {t.size}")
    for name, arr in (("pred", p), ("target", t)):
        if arr.size and (arr.min() < 0 or arr.max() >= num_classes):
            raise ValueError(f"{name} has class ids outside [0, {num_classes}): [{arr.min()}, {arr.max()}]")
    counts = np.bincount(t * num_classes + p, minlength=num_classes * num_classes)
    return counts.reshape(num_classes, num_classes).astype(np.int64)


def iou_from_confusion(conf: np.ndarray) -> np.ndarray:
    """Per-class IoU ``TP / (TP + FP + FN)`` from a ``conf[true, predicted]`` matrix, shape ``(C,)``.

    A class absent from both prediction and target has 0/0 IoU; it is returned as NaN (not 0 or 1) so that
    ``np.nanmean`` averages only over classes that actually occur instead of being inflated or deflated by
    classes the scene never contained.
    """
    conf = np.asarray(conf, dtype=np.int64)
    if conf.ndim != 2 or conf.shape[0] != conf.shape[1]:
        raise ValueError(f"confusion matrix must be square, got shape {conf.shape}")
    tp = np.diag(conf).astype(np.float64)
    denom = conf.sum(axis=0) + conf.sum(axis=1) - tp  # predicted + true - overlap
    iou = np.full(conf.shape[0], np.nan)
    present = denom > 0
    iou[present] = tp[present] / denom[present]
    return iou


def per_class_iou(pred, target, num_classes: int) -> np.ndarray:
    """Per-class IoU of one batch, shape ``(num_classes,)``; NaN for classes absent from both (see above)."""
    return iou_from_confusion(confusion(pred, target, num_classes))
