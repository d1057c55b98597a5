"""Parameter-free views of the segmentation frame for the agent (numpy only).

The world model's VAE compresses a 64×64 frame into 128 numbers, and a pedestrian 1-2 px wide at 30 m/s is what
it loses first (quick-scale Pedestrians IoU ~0.1, paper scale ~0.3). The camera itself sees that pedestrian: the
segmentation frame is exact. ``hazard_view`` hands the agent where the hazard classes are in the frame, at full
resolution along each axis, beside the latents (``agent.frame_view``; docs/design.md §5):

* per class, which image columns hold it (the bearing) and which rows hold it (on a flat road, the distance);
* the same for the previous frame, so that a crossing pedestrian's direction is visible from the second frame on.

Nothing here is privileged: it is a fixed function of the frames the camera gave.
"""

from __future__ import annotations

import numpy as np

from .scene import CLASS_NAMES

HAZARD_CLASSES = ("Pedestrians", "Vehicles")


def profiles(seg: np.ndarray, classes: tuple[str, ...] = HAZARD_CLASSES) -> np.ndarray:
    """``(H, W)`` class map -> ``(len(classes) * (W + H),)`` float32 in {0, 1}: for each class, the columns that
    hold it, then the rows that hold it."""
    seg = np.asarray(seg)
    if seg.ndim != 2:
        raise ValueError(f"expected an (H, W) class map, got shape {seg.shape}")
    parts = []
    for name in classes:
        mask = seg == CLASS_NAMES.index(name)
        parts += [mask.any(axis=0), mask.any(axis=1)]
    return np.concatenate(parts).astype(np.float32)


def view_dim(image_size: int, classes: tuple[str, ...] = HAZARD_CLASSES) -> int:
    """Length of ``HazardView``'s output for square frames: current and previous profiles."""
    return 2 * len(classes) * 2 * image_size


class HazardView:
    """The hazard profiles of the current and the previous frame (zeros before the first frame), as the agent
    reads them at every decision: ``reset()`` at episode start, then ``__call__(seg)`` once per frame."""

    def __init__(self, image_size: int = 64, classes: tuple[str, ...] = HAZARD_CLASSES):
        self.classes = tuple(classes)
        unknown = [c for c in self.classes if c not in CLASS_NAMES]
        if unknown:
            raise ValueError(f"unknown class names {unknown}; known: {list(CLASS_NAMES)}")
        self.dim = view_dim(image_size, self.classes)
        self.reset()

    def reset(self) -> None:
        self._previous = np.zeros(self.dim // 2, np.float32)

    def __call__(self, seg: np.ndarray) -> np.ndarray:
        current = profiles(seg, self.classes)
        if len(current) != self.dim // 2:
            raise ValueError(f"expected {self.dim // 4}-pixel square frames, got shape {np.shape(seg)}")
        out = np.concatenate([current, self._previous])
        self._previous = current
        return out


class MaskView:
    """Where the hazard classes are in a band of the frame, as 2-D masks: for each class the rows ``rows`` of the
    current and the previous frame (zeros before the first), flattened to ``(2 * len(classes) * band * W,)``.

    The profiles of ``HazardView`` are marginals: with a hazard pedestrian on the road and others on the
    sidewalks, which column goes with which row is lost. The band keeps it, around the horizon where road users
    between ~4 m and the far end of the street appear (the camera looks 8° down from 1.6 m)."""

    def __init__(self, rows: tuple[int, int] = (20, 44), image_size: int = 64, classes=HAZARD_CLASSES):
        self.classes = tuple(classes)
        unknown = [c for c in self.classes if c not in CLASS_NAMES]
        if unknown:
            raise ValueError(f"unknown class names {unknown}; known: {list(CLASS_NAMES)}")
        r0, r1 = int(rows[0]), int(rows[1])
        if not 0 <= r0 < r1 <= image_size:
            raise ValueError(f"mask rows {rows} must satisfy 0 <= first < last <= {image_size}")
        self.rows, self.image_size = (r0, r1), int(image_size)
        self.shape = (2 * len(self.classes), r1 - r0, self.image_size)  # channels: classes now, then before
        self.dim = int(np.prod(self.shape))
        self.reset()

    def reset(self) -> None:
        self._previous = np.zeros((len(self.classes), *self.shape[1:]), np.float32)

    def __call__(self, seg: np.ndarray) -> np.ndarray:
        seg = np.asarray(seg)
        if seg.shape != (self.image_size, self.image_size):
            raise ValueError(f"expected a ({self.image_size}, {self.image_size}) class map, got {seg.shape}")
        band = seg[self.rows[0] : self.rows[1]]
        current = np.stack([band == CLASS_NAMES.index(c) for c in self.classes]).astype(np.float32)
        out = np.concatenate([current, self._previous]).reshape(-1)
        self._previous = current
        return out
