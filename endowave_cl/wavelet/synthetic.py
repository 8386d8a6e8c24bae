"""A synthetic endoscopy-like test image: smooth reddish tissue under a vignetting light, darker
vessels, fine texture, and small saturated specular highlights (used by tools/compare_wavelets.py
and research/tune_wavelet.py)."""
from __future__ import annotations

from typing import Tuple

import numpy as np


def synthetic_endoscopy_image(h: int = 256, w: int = 320, seed: int = 0,
                              n_highlights: int = 14) -> Tuple[np.ndarray, np.ndarray]:
    """(image [h, w, 3] float32 in [0, 1], highlight mask [h, w] bool).

    The mask marks pixels where the specular term exceeds 0.1 (before clipping)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    yn, xn = (y - h / 2) / (h / 2), (x - w / 2) / (w / 2)
    # light falloff (vignetting) and smooth albedo undulation
    light = np.clip(1.0 - 0.45 * (xn ** 2 + yn ** 2), 0.15, 1.0)
    und = 0.08 * np.sin(2.1 * xn + 0.7) * np.cos(1.7 * yn - 0.4) + 0.05 * np.sin(3.3 * (xn + yn))
    base = np.stack([0.78 + und, 0.36 + 0.6 * und, 0.30 + 0.5 * und], -1)
    # vessels: a few wavy dark lines of width ~1.5-3 px
    vess = np.zeros((h, w))
    for _ in range(5):
        a0, f0, ph, off = rng.uniform(5, 25), rng.uniform(0.01, 0.04), rng.uniform(0, 6.3), rng.uniform(0.1, 0.9) * h
        width = rng.uniform(0.8, 1.6)
        dist = y - (off + a0 * np.sin(f0 * x + ph))
        vess = np.maximum(vess, np.exp(-0.5 * (dist / width) ** 2))
    base = base * (1 - 0.45 * vess[..., None] * np.array([0.5, 1.0, 1.0]))
    # fine texture
    from scipy.ndimage import gaussian_filter   # scipy: not a declared dependency (scikit-image brings it)
    tex = gaussian_filter(rng.normal(0, 1, (h, w)), 1.5)
    tex /= tex.std() + 1e-12
    base = base * (1 + 0.03 * tex[..., None])
    img = base * light[..., None]
    # specular highlights: small elongated near-white blobs (sigma 0.7 .. 2.5 px)
    spec = np.zeros((h, w))
    for _ in range(n_highlights):
        cy, cx = rng.uniform(0.1, 0.9) * h, rng.uniform(0.1, 0.9) * w
        sy, sx = rng.uniform(0.7, 2.5), rng.uniform(0.7, 2.5)
        spec += rng.uniform(0.6, 1.0) * np.exp(-0.5 * (((y - cy) / sy) ** 2 + ((x - cx) / sx) ** 2))
    img = img + spec[..., None] * np.array([1.0, 0.97, 0.95])
    return np.clip(img, 0.0, 1.0).astype(np.float32), spec > 0.1
