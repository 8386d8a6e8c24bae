"""The rational-wavelet loss: a torch autograd Function backed by the OpenCL kernels, and a pure-torch
implementation of the same function (WaveletConfig and the device entry point wavelet_loss_and_grad
live in config.py, torch-free, and are re-exported here).

    L = sum_{j < levels} sum_{x in LL, LH, HL, HH} lambda_x * mean((W_x^j(m t) - W_x^j(m r))^2)

r = rendered, t = target, both [H, W, C]; m = the [H, W] mask (1 = supervise), which multiplies
both images before the transform when given.  "mean" is over the H_j * W_j * C coefficients of the
band, so every band of every level counts by its average squared error whatever its size.
"""
from __future__ import annotations

from typing import Dict, List, Optional

import numpy as np
import torch
import torch.nn.functional as F

from .config import BORDERS, WaveletConfig, wavelet_loss_and_grad  # noqa: F401  (re-exported)
from .filters import BAND_FILTERS, BANDS, design_filters, rational_factor, reflect_index, resampled_length


# ---------------------------------------------------------------------------------------------
# pure torch (any device, any float dtype; autograd gives the adjoint)
# ---------------------------------------------------------------------------------------------

def torch_conv_axis(x: torch.Tensor, f, axis: int) -> torch.Tensor:
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


def torch_resample_axis(x: torch.Tensor, q: int, axis: int) -> torch.Tensor:
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


def torch_decompose(img: torch.Tensor, q: int, levels: int = 2) -> List[Dict[str, torch.Tensor]]:
    """J-level transform of img [H, W, C] in torch."""
    filt = design_filters(q)
    out = []
    cur = img
    for _ in range(int(levels)):
        rows = {k: torch_resample_axis(torch_conv_axis(cur, filt[k], 1), q, 1) for k in ("h0", "h1", "g")}
        bands = {}
        for band in BANDS:
            fr, fc = BAND_FILTERS[band]
            bands[band] = torch_resample_axis(torch_conv_axis(rows[fr], filt[fc], 0), q, 0)
        out.append(bands)
        cur = bands["LL"]
    return out


def torch_wavelet_loss(rendered: torch.Tensor, target: torch.Tensor, mask: Optional[torch.Tensor] = None,
                       config: WaveletConfig = WaveletConfig()) -> torch.Tensor:
    """The same loss in pure torch; rendered, target [H, W, C], mask [H, W] or None."""
    d = rendered - target  # the transform is linear: W(t) - W(r) = -W(r - t)
    if mask is not None:
        d = d * mask.unsqueeze(-1)
    total = d.new_zeros(())
    for bands in torch_decompose(d, config.q, config.levels):
        for band, lam in zip(BANDS, config.weights):
            total = total + lam * bands[band].square().mean()
    return total


# ---------------------------------------------------------------------------------------------
# torch autograd Function backed by the kernels, and a module for other trainers
# ---------------------------------------------------------------------------------------------

def _to_device(rt, t: torch.Tensor):
    import pyopencl.array as cla
    return cla.to_device(rt.queue, np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy()))


class WaveletLossFunction(torch.autograd.Function):
    """loss = WaveletLossFunction.apply(rendered [H,W,C], target [H,W,C], mask [H,W] | None,
    config, rt | None).

    Forward and gradient come from the OpenCL kernels (one call computes both); the tensors are
    copied to and from the OpenCL device (rt None: the default runtime).  Gradients flow to
    rendered and to target (= -v_rendered), not to the mask.
    """

    @staticmethod
    def forward(ctx, rendered, target, mask, config, rt=None):
        if rt is None:
            from ..runtime import get_runtime
            rt = get_runtime()
        if config is None:
            config = WaveletConfig()
        r = _to_device(rt, rendered)
        t = _to_device(rt, target)
        m = None if mask is None else _to_device(rt, mask)
        loss, v = wavelet_loss_and_grad(rt, r, t, m, config)
        ctx.save_for_backward(torch.from_numpy(v.get()).to(rendered.device, rendered.dtype))
        return rendered.new_tensor(loss)

    @staticmethod
    def backward(ctx, grad_out):
        (v,) = ctx.saved_tensors
        g_r = grad_out * v if ctx.needs_input_grad[0] else None
        g_t = -grad_out * v if ctx.needs_input_grad[1] else None
        return g_r, g_t, None, None, None


class RationalWaveletLoss(torch.nn.Module):
    """Plug-in loss for torch trainers (e.g. Endo-4DGS, as in the paper's Table).

    backend "opencl" runs the kernels (WaveletLossFunction), "torch" the pure-torch version.
    layout "hwc" takes [H, W, C] images; "chw" takes [C, H, W] or [B, C, H, W] (batch averaged).
    mask: [H, W] (or [B, 1, H, W] / [B, H, W] with "chw") or None.
    """

    def __init__(self, config: WaveletConfig = WaveletConfig(), backend: str = "opencl",
                 layout: str = "hwc", rt=None):
        super().__init__()
        if backend not in ("opencl", "torch"):
            raise ValueError("backend must be 'opencl' or 'torch'")
        if layout not in ("hwc", "chw"):
            raise ValueError("layout must be 'hwc' or 'chw'")
        self.config, self.backend, self.layout, self._rt = config, backend, layout, rt

    @property
    def rt(self):
        if self._rt is None:
            from ..runtime import get_runtime
            self._rt = get_runtime()
        return self._rt

    def _one(self, r, t, m):
        if self.backend == "torch":
            return torch_wavelet_loss(r, t, m, self.config)
        return WaveletLossFunction.apply(r, t, m, self.config, self.rt)

    def forward(self, rendered, target, mask=None):
        if self.layout == "hwc":
            return self._one(rendered, target, mask)
        if rendered.dim() == 3:
            rendered, target = rendered[None], target[None]
            mask = None if mask is None else mask.reshape(1, *mask.shape[-2:])
        losses = []
        for b in range(rendered.shape[0]):
            m = None if mask is None else mask[b].reshape(mask.shape[-2:])
            losses.append(self._one(rendered[b].permute(1, 2, 0), target[b].permute(1, 2, 0), m))
        return torch.stack(losses).mean()
