"""Torch references of the rational-wavelet transform and loss (any device, any float dtype; torch
autograd gives the adjoint): conv_axis_ref, resample_axis_ref, decompose_ref, wavelet_loss_ref.

The device ops are in endowave_cl/wavelet/ops.py (conv_axis / conv_axis_bwd, resample_axis /
resample_axis_bwd, decompose / decompose_bwd, loss_and_grad); the numpy reference transform of the
filter design is in endowave_cl/wavelet/filters.py.  See docs/WAVELET.md.
"""
from __future__ import annotations

from typing import Dict, List, Optional

import numpy as np
import torch
import torch.nn.functional as F

from ..wavelet.config import WaveletConfig
from ..wavelet.filters import BAND_FILTERS, BANDS, design_filters, rational_factor, reflect_index, resampled_length



def conv_axis_ref(x: torch.Tensor, f, axis: int) -> torch.Tensor:
    """Convolution along axis with the odd-length filter f, reflect border (as cl conv_axis)."""
    f = torch.as_tensor(np.asarray(f, dtype=np.float64), dtype=x.dtype, device=x.device)
    L = f.numel()
    R = L // 2
    xt = x.movedim(axis, -1)
    lead = xt.shape[:-1]
    n = xt.shape[-1]
    idx = torch.as_tensor(reflect_index(np.arange(-R, n + R), n), device=x.device)
    padded = xt.reshape(-1, 1, n).index_select(-1, idx)               # [B, 1, n + 2R]
    out = F.conv1d(padded, f.flip(0).view(1, 1, L))                     # [B, 1, n]
    return out.reshape(*lead, n).movedim(-1, axis)


def resample_axis_ref(x: torch.Tensor, q: int, axis: int) -> torch.Tensor:
    """Rational resampling by a = (q + 1) / q along axis (as cl resample_axis)."""
    p, q = rational_factor(q)
    n = x.shape[axis]
    n_out = resampled_length(n, q)
    j = np.arange(n_out) * p
    i0 = j // q
    w = torch.as_tensor((j - i0 * q) / q, dtype=x.dtype, device=x.device)
    i1 = np.minimum(i0 + 1, n - 1)
    x0 = x.index_select(axis, torch.as_tensor(i0, device=x.device))
    x1 = x.index_select(axis, torch.as_tensor(i1, device=x.device))
    shape = [1] * x.dim()
    shape[axis] = n_out
    w = w.view(shape)
    return x0 * (1 - w) + x1 * w


def decompose_ref(img: torch.Tensor, q: int, levels: int = 2) -> List[Dict[str, torch.Tensor]]:
    """J-level transform of img [H, W, C] in torch."""
    filt = design_filters(q)
    out = []
    cur = img
    for _ in range(int(levels)):
        rows = {k: resample_axis_ref(conv_axis_ref(cur, filt[k], 1), q, 1) for k in ("h0", "h1", "g")}
        bands = {}
        for band in BANDS:
            fr, fc = BAND_FILTERS[band]
            bands[band] = resample_axis_ref(conv_axis_ref(rows[fr], filt[fc], 0), q, 0)
        out.append(bands)
        cur = bands["LL"]
    return out


def wavelet_loss_ref(rendered: torch.Tensor, target: torch.Tensor, mask: Optional[torch.Tensor] = None,
                     config: WaveletConfig = WaveletConfig()) -> torch.Tensor:
    """The same loss in pure torch; rendered, target [H, W, C], mask [H, W] or None."""
    d = rendered - target  # the transform is linear: W(t) - W(r) = -W(r - t)
    if mask is not None:
        d = d * mask.unsqueeze(-1)
    total = d.new_zeros(())
    for bands in decompose_ref(d, config.q, config.levels):
        for band, lam in zip(BANDS, config.weights):
            total = total + lam * bands[band].square().mean()
    return total
