"""The rational-wavelet loss for torch users: an autograd Function backed by the OpenCL kernels and an
nn.Module over it or over the pure-torch reference (reference/wavelet.py: wavelet_loss_ref).
WaveletConfig and the device entry point wavelet_loss_and_grad live in config.py, torch-free, and
are re-exported here.

    L = sum_{j < levels} sum_{x in LL, LH, HL, HH} lambda_x * mean((W_x^j(m t) - W_x^j(m r))^2)

r = rendered, t = target, both [H, W, C]; m = the [H, W] mask (1 = supervise), which multiplies
both images before the transform when given.  "mean" is over the H_j * W_j * C coefficients of the
band, so every band of every level counts by its average squared error whatever its size.
"""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import torch

from ..reference.wavelet import wavelet_loss_ref
from ..runtime import get_runtime
from .config import BORDERS, WaveletConfig, wavelet_loss_and_grad  # noqa: F401  (re-exported)


# ---------------------------------------------------------------------------------------------
# torch autograd Function backed by the kernels, and a module for other trainers
# ---------------------------------------------------------------------------------------------

def _to_device(rt, t: torch.Tensor):
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
            self._rt = get_runtime()
        return self._rt

    def _one(self, r, t, m):
        if self.backend == "torch":
            return wavelet_loss_ref(r, t, m, self.config)
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
