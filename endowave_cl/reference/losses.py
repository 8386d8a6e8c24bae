"""Image-space training losses in torch: the definitions, and the reference of the device version.

The trainer computes the same functions, and their gradient images for rasterize_bwd, with the
OpenCL kernels of endowave_cl/train/device_losses.py (cl/image_loss.cl); tests/kernels/test_device_losses.py
checks them against ``image_losses_ref`` here and its torch autograd gradient.

Images are channel-last float tensors: image [H, W, 3], depth [H, W], flow [H, W, 2];
mask [H, W] with 1 = supervise (tissue), 0 = ignore (tool).  Every "masked mean" divides by the
number of supervised pixels (x channels), so a loss does not shrink when the tool covers more.

Choices (DESIGN.md leaves them open):
- D-SSIM under a mask: both images are multiplied by the mask first (tool pixels become equal
  zeros, so they add no error to the windows around them), then the SSIM map is averaged over
  the supervised pixels.  SSIM itself is 3DGS's: 11 x 11 Gaussian window, sigma 1.5, zero
  padding, C1 = 0.01^2, C2 = 0.03^2, per channel.
- Depth: L1 between the rendered depth as composited (sum of z alpha T, NOT divided by the
  accumulated alpha) and the ground truth on pixels with gt > 0 and mask.  Endoscopic tissue
  covers every pixel, so an unnormalised depth also pulls the accumulated alpha to 1 (no holes),
  and it avoids dividing by alpha ~ 0 where nothing has been rendered yet.
- Flow: mean over valid pixels of the squared endpoint error |f_pred - f_gt|^2 (pixels^2), the
  per-pixel form of the paper's L2 term.  The squared form is smooth at 0 (the plain norm's
  gradient is undefined there) and, unlike the norm of the whole masked field as the paper writes
  it, does not grow with the image size.  Beyond an error of ``delta`` pixels (config
  ``flow_huber_delta``, default 4) it continues linearly (Huber: 2 delta |e| - delta^2, same value
  and slope at delta), so one pixel's gradient is at most 2 delta.  Without that bound, Gaussians
  whose velocity Sigma_xt / Sigma_tt runs away render flows far beyond the image, and the squared
  term takes over training (the measurement: research/SUMMARY.md, "Choices the paper leaves open").
"""
from __future__ import annotations

import math
from typing import Callable, Dict, Mapping, Optional, Tuple

import torch
import torch.nn.functional as F

from ..loss_constants import FLOW_HUBER_DELTA, SSIM_C1, SSIM_C2, SSIM_SIGMA, SSIM_WINDOW  # noqa: F401


def _gaussian_window_1d(size: int, sigma: float, dtype, device) -> torch.Tensor:
    # loss_constants.gaussian_window_1d in torch, computed in the images' dtype
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2.0
    g = torch.exp(-x * x / (2 * sigma * sigma))
    return g / g.sum()  # [size]; the 2D window is its outer product


def ssim_map(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Per-pixel, per-channel SSIM of [H, W, C] images (3DGS's definition); returns [H, W, C].

    The 11 x 11 Gaussian window is separable, so the five local means are computed in one batched
    pair of 1D convolutions (rows, then columns); with zero padding this equals the 2D convolution.
    The maps stay channel-last (torch's channels_last format): torch's CPU depthwise convolution
    is faster there than on NCHW planes, forward and backward (docs/ARCHITECTURE.md, Figures).
    """
    C = pred.shape[-1]
    g = _gaussian_window_1d(SSIM_WINDOW, SSIM_SIGMA, pred.dtype, pred.device)
    pad = SSIM_WINDOW // 2
    stack = torch.cat([pred, gt, pred * pred, gt * gt, pred * gt], -1)   # [H, W, 5C]
    # [1, 5C, H, W] with channels_last strides (the batch dimension added before the permute:
    # torch only takes its channels_last kernels when every stride, that of N too, is the format's)
    stack = stack.unsqueeze(0).permute(0, 3, 1, 2)
    n = stack.shape[1]
    wr = g.view(1, 1, 1, -1).expand(n, 1, 1, SSIM_WINDOW)
    wc = g.view(1, 1, -1, 1).expand(n, 1, SSIM_WINDOW, 1)
    blurred = F.conv2d(F.conv2d(stack, wr, padding=(0, pad), groups=n), wc, padding=(pad, 0), groups=n)
    # back to five contiguous [H, W, C] maps (element-wise maths on interleaved views is slow)
    H, W = pred.shape[:2]
    maps = blurred.permute(0, 2, 3, 1).reshape(H, W, 5, C).permute(2, 0, 1, 3).contiguous()  # [5, H, W, C]
    mu_x, mu_y, exx, eyy, exy = maps.unbind(0)
    sxx = exx - mu_x * mu_x
    syy = eyy - mu_y * mu_y
    sxy = exy - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sxy + SSIM_C2)
    den = (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (sxx + syy + SSIM_C2)
    return num / den


def _mask_like(mask: Optional[torch.Tensor], ref: torch.Tensor) -> torch.Tensor:
    if mask is None:
        return torch.ones(ref.shape[:2], dtype=ref.dtype, device=ref.device)
    return mask.to(ref.dtype)


def _masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of x [H, W] or [H, W, C] over pixels with mask [H, W] > 0; 0 when none are."""
    m = mask if x.dim() == 2 else mask.unsqueeze(-1)
    channels = 1 if x.dim() == 2 else x.shape[-1]
    count = mask.sum() * channels
    return (x * m).sum() / torch.clamp(count, min=1.0)


def rgb_terms(pred: torch.Tensor, gt: torch.Tensor, mask: Optional[torch.Tensor] = None
              ) -> Tuple[torch.Tensor, torch.Tensor]:
    """(masked L1, masked mean SSIM) of [H, W, 3] images."""
    m = _mask_like(mask, pred)
    l1 = _masked_mean((pred - gt).abs(), m)
    mm = m.unsqueeze(-1)
    ssim = _masked_mean(ssim_map(pred * mm, gt * mm), m)
    return l1, ssim


def rgb_loss(pred: torch.Tensor, gt: torch.Tensor, mask: Optional[torch.Tensor] = None,
             lambda_dssim: float = 0.2) -> torch.Tensor:
    """(1 - lambda_dssim) L1 + lambda_dssim (1 - SSIM), masked (3DGS: 0.8 L1 + 0.2 D-SSIM)."""
    l1, ssim = rgb_terms(pred, gt, mask)
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim)


def depth_loss(pred_depth: torch.Tensor, gt_depth: torch.Tensor, mask: Optional[torch.Tensor] = None
               ) -> torch.Tensor:
    """L1 over pixels with gt_depth > 0 and mask (depth [H, W], as composited; see module doc)."""
    valid = (gt_depth > 0).to(pred_depth.dtype) * _mask_like(mask, pred_depth)
    return _masked_mean((pred_depth - gt_depth).abs(), valid)


def flow_loss(pred_flow: torch.Tensor, gt_flow: torch.Tensor, valid: Optional[torch.Tensor] = None,
              delta: float = FLOW_HUBER_DELTA) -> torch.Tensor:
    """Mean over valid pixels of the squared endpoint error |e|^2 [pixels^2], continued linearly
    as 2 delta |e| - delta^2 beyond |e| = delta (flow [H, W, 2], valid [H, W]; delta = inf: pure
    squared error)."""
    v = _mask_like(valid, pred_flow)
    sq = ((pred_flow - gt_flow) ** 2).sum(-1)
    if math.isfinite(delta):
        d2 = delta * delta
        lin = 2.0 * delta * torch.sqrt(torch.clamp(sq, min=d2)) - d2   # no sqrt(0) gradient
        sq = torch.where(sq <= d2, sq, lin)
    return _masked_mean(sq, v)


def _f(x: torch.Tensor) -> float:
    return float(x.detach())


WaveletLoss = Callable[[torch.Tensor, torch.Tensor, Optional[torch.Tensor]], torch.Tensor]


def image_losses_ref(pred: Mapping[str, torch.Tensor], target: Mapping[str, Optional[torch.Tensor]], cfg,
                 wavelet_loss: Optional[WaveletLoss] = None) -> Tuple[torch.Tensor, Dict[str, float]]:
    """The total training loss of one frame and its parts (floats, for logging).

    pred: image [H, W, 3], depth [H, W] (needed when depth is used), flow [H, W, 2] (when flow is).
    target: image, and optionally depth, mask, flow, flow_valid (None or absent = not available).
    cfg: a TrainConfig (lambda_*, use_depth, use_flow, use_wavelet).
    wavelet_loss(pred_image, gt_image, mask) -> scalar: the rational-wavelet term, added (weighted
    by cfg.lambda_wavelet, when cfg.use_wavelet) only when given: a trainer that computes the
    wavelet loss and its gradient on the device adds them itself and passes None here.
    Terms whose inputs are missing (no depth maps, no flow for this frame) are left out.
    """
    mask = target.get("mask")
    img, gt = pred["image"], target["image"]
    parts: Dict[str, float] = {}
    l1, ssim = rgb_terms(img, gt, mask)
    rgb = (1.0 - cfg.lambda_dssim) * l1 + cfg.lambda_dssim * (1.0 - ssim)
    total = cfg.lambda_rgb * rgb
    parts.update(l1=_f(l1), ssim=_f(ssim), rgb=_f(rgb))
    if cfg.use_depth and cfg.lambda_depth > 0 and target.get("depth") is not None:
        d = depth_loss(pred["depth"], target["depth"], mask)
        total = total + cfg.lambda_depth * d
        parts["depth"] = _f(d)
    if cfg.use_flow and cfg.lambda_flow > 0 and target.get("flow") is not None:
        valid = target.get("flow_valid")
        if mask is not None:  # no flow supervision on tool pixels either
            valid = mask if valid is None else valid.to(mask.dtype) * mask
        f = flow_loss(pred["flow"], target["flow"], valid, getattr(cfg, "flow_huber_delta", FLOW_HUBER_DELTA))
        total = total + cfg.lambda_flow * f
        parts["flow"] = _f(f)
    if cfg.use_wavelet and cfg.lambda_wavelet > 0 and wavelet_loss is not None:
        w = wavelet_loss(img, gt, mask)
        total = total + cfg.lambda_wavelet * w
        parts["wavelet"] = _f(w)
    parts["total"] = _f(total)
    return total, parts
