"""Rational-wavelet transform and loss (paper: "Rational Wavelet Decomposition").

filters.py  filter design (h0, h1, g for a = (q + 1) / q) and the numpy reference transform
ops.py      OpenCL host ops: convolution / resampling along an axis and adjoints, decompose,
            v_decompose, loss_and_grad (kernels in cl/wavelet.cl)
loss.py     WaveletConfig, wavelet_loss_and_grad (the trainer's entry point), the pure-torch loss,
            the autograd Function and nn.Module
See docs/WAVELET.md.
"""
from .filters import BANDS, design_filters, level_shapes, resampled_length, support_radius
from .loss import (RationalWaveletLoss, WaveletConfig, WaveletLossFunction, torch_decompose,
                   torch_wavelet_loss, wavelet_loss_and_grad, wavelet_transform)

__all__ = ["BANDS", "design_filters", "level_shapes", "resampled_length", "support_radius",
           "RationalWaveletLoss", "WaveletConfig", "WaveletLossFunction", "torch_decompose",
           "torch_wavelet_loss", "wavelet_loss_and_grad", "wavelet_transform"]
