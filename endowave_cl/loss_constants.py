"""Constants of the image losses, shared by the torch reference (reference/losses.py) and the device
version (train/device_losses.py), and the SSIM window in numpy, so that the device side does not
import torch."""
from __future__ import annotations

import numpy as np

SSIM_WINDOW = 11       # 3DGS: 11 x 11 Gaussian window ...
SSIM_SIGMA = 1.5       # ... of standard deviation 1.5 pixels
SSIM_C1 = 0.01 ** 2    # (K1 L)^2 with K1 = 0.01, data range L = 1
SSIM_C2 = 0.03 ** 2    # (K2 L)^2 with K2 = 0.03

FLOW_HUBER_DELTA = 4.0   # pixels: the flow error beyond which the flow loss grows linearly


def gaussian_window_1d(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
    """[size] float64 normalised 1D Gaussian; the 2D SSIM window is its outer product.  The same
    formula as reference/losses.py's torch window (equal to it in float64; that one is built in the
    dtype of the images it compares, so its float32 results are unchanged)."""
    x = np.arange(size, dtype=np.float64) - (size - 1) / 2.0
    g = np.exp(-x * x / (2 * sigma * sigma))
    return g / g.sum()
