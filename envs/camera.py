"""Off-screen segmentation camera (pybullet TinyRenderer, DIRECT mode).

The camera rides above the ego's roof, 0.5 m ahead of its centre at 1.6 m, pitched 8 degrees down. It sits
outside every body the ego can touch before an episode ends (TinyRenderer can hang with the eye inside a
body), and the ego itself has no body in the forward view.

The field of view (90 degrees by default) was chosen from a measurement: ``benchmarks/bench_env.py``
reports the share of test-bank scenarios whose hazard is visible at onset per TTC x speed cell.
"""
from __future__ import annotations

import math

import numpy as np

from .scene import PALETTE

EYE_FORWARD = 0.5
EYE_HEIGHT = 1.6
PITCH_DEG = 8.0
NEAR, FAR = 0.1, 70.0


class SegmentationCamera:
    def __init__(self, client: int, lut: np.ndarray, size: int = 64, fov_deg: float = 90.0):
        import pybullet as p

        self._p = p
        self.client = client
        self.lut = lut
        self.size = size
        self.projection = p.computeProjectionMatrixFOV(fov_deg, 1.0, NEAR, FAR, physicsClientId=client)
        self.last_uids = np.full((size, size), -1, dtype=np.int32)

    def _view(self, x: float, y: float, heading: float) -> list:
        c, s = math.cos(heading), math.sin(heading)
        eye = (x + EYE_FORWARD * c, y + EYE_FORWARD * s, EYE_HEIGHT)
        drop = math.tan(math.radians(PITCH_DEG)) * 10.0
        target = (eye[0] + 10.0 * c, eye[1] + 10.0 * s, EYE_HEIGHT - drop)
        return self._p.computeViewMatrix(eye, target, (0.0, 0.0, 1.0), physicsClientId=self.client)

    def _render_uids(self, view, size: int, projection) -> np.ndarray:
        _, _, _, _, seg = self._p.getCameraImage(
            size, size, view, projection, renderer=self._p.ER_TINY_RENDERER, physicsClientId=self.client)
        seg = np.asarray(seg, dtype=np.int64).reshape(size, size)
        # Low 24 bits carry the body uid; background is -1.
        return np.where(seg < 0, -1, seg & 0xFFFFFF).astype(np.int32)

    def render(self, x: float, y: float, heading: float) -> np.ndarray:
        """Class-id frame (size, size) uint8 seen from the ego pose."""
        self.last_uids = self._render_uids(self._view(x, y, heading), self.size, self.projection)
        return self.lut[self.last_uids + 1]

    def birds_eye(self, x: float, y: float, heading: float, size: int = 128, span: float = 60.0) -> np.ndarray:
        """Top-down class map centred ahead of the ego, forward pointing up the image."""
        p = self._p
        c, s = math.cos(heading), math.sin(heading)
        centre = (x + 0.3 * span * c, y + 0.3 * span * s, 0.0)
        height = 150.0
        fov = math.degrees(2.0 * math.atan(0.5 * span / height))
        view = p.computeViewMatrix((centre[0], centre[1], height), centre, (c, s, 0.0), physicsClientId=self.client)
        proj = p.computeProjectionMatrixFOV(fov, 1.0, 1.0, 400.0, physicsClientId=self.client)
        return self._render_uids(view, size, proj)


def colorize(classes: np.ndarray) -> np.ndarray:
    """Class ids -> RGB with the CARLA palette."""
    return PALETTE[np.asarray(classes, dtype=np.intp)]
