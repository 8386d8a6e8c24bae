"""Rational-wavelet transform and loss (paper: "Rational Wavelet Decomposition").

filters.py  filter design (h0, h1, g for a = (q + 1) / q) and the numpy reference transform
ops.py      OpenCL host ops: convolution / resampling along an axis and adjoints, decompose,
            decompose_bwd, loss_and_grad (kernels in cl/wavelet.cl)
config.py   WaveletConfig and wavelet_loss_and_grad (the trainer's entry point), torch-free
loss.py     the autograd Function and nn.Module (torch); the pure-torch references are in
            endowave_cl/reference/wavelet.py (decompose_ref, wavelet_loss_ref)
See docs/WAVELET.md.  The names from loss.py are loaded on first use, so that importing
endowave_cl.wavelet, .ops or .config (the device path) does not import torch.
"""
from .config import WaveletConfig, wavelet_loss_and_grad
from .filters import BANDS, design_filters, level_shapes, resampled_length, support_radius

_FROM_LOSS = ("RationalWaveletLoss", "WaveletLossFunction")

__all__ = ["BANDS", "design_filters", "level_shapes", "resampled_length", "support_radius",
           "WaveletConfig", "wavelet_loss_and_grad", *_FROM_LOSS]


def __getattr__(name):
    if name in _FROM_LOSS:
        from . import loss     # on first use: loss.py imports torch (see above)
        return getattr(loss, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
