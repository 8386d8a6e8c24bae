"""Pinhole camera in the OpenCV convention (x right, y down, z forward)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Camera:
    fx: float
    fy: float
    cx: float                    # principal point in pixels; pixel (i, j) covers [i, i+1) x [j, j+1),
    cy: float                    # so its centre is at (i + 0.5, j + 0.5)
    width: int
    height: int
    viewmat: np.ndarray = field(default_factory=lambda: np.eye(4, dtype=np.float32))  # [4, 4] world -> camera
    near: float = 0.01           # Gaussians whose camera-space z is below this are culled

    def __post_init__(self):
        self.viewmat = np.asarray(self.viewmat, dtype=np.float32).reshape(4, 4)
        self.width = int(self.width)
        self.height = int(self.height)

    @property
    def K(self) -> np.ndarray:  # [3, 3]
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], np.float32)

    @property
    def campos(self) -> np.ndarray:  # [3] camera centre in world coordinates
        R = self.viewmat[:3, :3].astype(np.float64)
        t = self.viewmat[:3, 3].astype(np.float64)
        return (-R.T @ t).astype(np.float32)

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image downscaled by ``factor`` (2 = half size)."""
        return Camera(self.fx / factor, self.fy / factor, self.cx / factor, self.cy / factor,
                      int(round(self.width / factor)), int(round(self.height / factor)),
                      self.viewmat.copy(), self.near)
