"""Rational-wavelet filter design and the numpy reference transform.

Filters (paper, "Rational Wavelet Decomposition", eqs. h0, h1, g), for the rational
scale factor a = p / q = (q + 1) / q and the bandwidth sigma = 1 / a, on the integer
taps t = -R .. R:

    h0(t) = exp(-t^2 / (2 sigma^2))                 / sum_u exp(-u^2 / (2 sigma^2))
    h1(t) = -t exp(-t^2 / (2 sigma^2))              / sum_u |u exp(-u^2 / (2 sigma^2))|
    g(t)  = sin(pi t / a) exp(-t^2 / (2 (2 sigma)^2)) / sum_u |sin(pi u / a) exp(-u^2 / (8 sigma^2))|

Support: R = ceil(SUPPORT_STDS * 2 sigma) = ceil(8 / a), i.e. four standard deviations of the
widest Gaussian (the one in g, width 2 sigma).  One support is shared by all three filters so
that every normalising sum runs over the same taps.  q = 1 (a = 2) gives R = 4 (9 taps);
q = 2, 3 give R = 6 (13 taps); q = 4..7 give R = 7 (15 taps); q >= 8 gives R = 8 (17 taps,
never more, since a > 1).

Conventions used by every implementation (numpy here, OpenCL in ops.py, torch in loss.py):

* Images are channel-last [H, W, C].  "Rows" (*_r) means filtering along W (within each row),
  "columns" (*_c) along H.
* Convolution (not correlation): out[x] = sum_{t=-R..R} f(t) in[x - t].  (h1 and g are odd, so
  the choice flips their sign; the paper writes a convolution.)
* Border: whole-sample symmetric reflection, index -1 -> 1, N -> N - 2 (numpy 'reflect'),
  repeated as often as needed, so any N >= 1 works (N = 1 reflects everything onto sample 0).
  The output has the same length as the input.
* Rational resampling by a = p / q: out[n] = in(n * p / q) read by linear interpolation, for every
  n with n * p / q <= N - 1, so N_out = floor((N - 1) q / p) + 1 and no border is needed.  This is
  exactly the polyphase resampler "up by q, filter with the triangle of half-width q, down by p";
  the phases n p mod q are integers, so it is exact.  For q = 1 (a = 2) the triangle is a single
  tap and out[n] = in[2 n]: plain dyadic downsampling, N_out = ceil(N / 2).
* One level: rows filtered by h0, h1 and g and resampled along W; then columns filtered and
  resampled along H:  LL = (I *_r h0) *_c h0,  LH = (I *_r h0) *_c h1,  HL = (I *_r h1) *_c h0,
  HH = (I *_r g) *_c g, each resampled by a on both axes.  (Resampling along W commutes with
  filtering along H, so resampling each axis right after its own filter is the same operator.)
  LL of level j is the input of level j + 1.
"""
from __future__ import annotations

import math
from typing import Dict, List, Tuple

import numpy as np

# Support half-width in standard deviations of the widest Gaussian (g's, width 2 sigma).
# exp(-0.5 * 4^2) = 3.4e-4 of the peak: the truncated tail changes no tap by more than that.
SUPPORT_STDS = 4.0

BANDS = ("LL", "LH", "HL", "HH")
# (row filter, column filter) of each band, as in the paper's equation.
BAND_FILTERS = {"LL": ("h0", "h0"), "LH": ("h0", "h1"), "HL": ("h1", "h0"), "HH": ("g", "g")}


def rational_factor(q: int) -> Tuple[int, int]:
    """(p, q) with a = p / q = (q + 1) / q."""
    q = int(q)
    if q < 1:
        raise ValueError(f"q must be an integer >= 1, got {q}")
    return q + 1, q


def support_radius(q: int) -> int:
    """R: the filters have 2 R + 1 taps."""
    p, q = rational_factor(q)
    sigma = q / p  # 1 / a
    return int(math.ceil(SUPPORT_STDS * 2.0 * sigma - 1e-9))


def design_filters(q: int, radius: int | None = None) -> Dict[str, np.ndarray]:
    """h0, h1, g as float64 arrays of length 2 R + 1; entry i is the tap t = i - R."""
    p, q = rational_factor(q)
    a = p / q
    sigma = 1.0 / a
    R = support_radius(q) if radius is None else int(radius)
    t = np.arange(-R, R + 1, dtype=np.float64)
    gauss = np.exp(-0.5 * (t / sigma) ** 2)
    h0 = gauss / gauss.sum()
    d = -t * gauss
    h1 = d / np.abs(d).sum()
    m = np.sin(np.pi * t / a) * np.exp(-0.5 * (t / (2.0 * sigma)) ** 2)
    g = m / np.abs(m).sum()
    return {"h0": h0, "h1": h1, "g": g}


def resampled_length(n: int, q: int) -> int:
    """Length after resampling n samples by a = (q + 1) / q."""
    p, q = rational_factor(q)
    return (int(n) - 1) * q // p + 1


def level_shapes(h: int, w: int, q: int, levels: int) -> List[Tuple[int, int]]:
    """Band (H, W) of each level."""
    out = []
    for _ in range(levels):
        h, w = resampled_length(h, q), resampled_length(w, q)
        out.append((h, w))
    return out


# ----------------------------------------------------------------------------------------------
# numpy reference (float64), axis-generic
# ----------------------------------------------------------------------------------------------

def reflect_index(m: np.ndarray, n: int) -> np.ndarray:
    """Whole-sample symmetric reflection of integer positions m into [0, n)."""
    m = np.asarray(m, dtype=np.int64)
    if n == 1:
        return np.zeros_like(m)
    period = 2 * (n - 1)
    r = np.mod(m, period)
    return np.where(r < n, r, period - r)


def conv_axis(x: np.ndarray, f: np.ndarray, axis: int) -> np.ndarray:
    """Convolution of x with the odd-length filter f along axis, reflect border, same length."""
    f = np.asarray(f, dtype=np.float64)
    if f.ndim != 1 or f.size % 2 != 1:
        raise ValueError("filter must be 1-D with odd length")
    R = f.size // 2
    x = np.moveaxis(np.asarray(x, dtype=np.float64), axis, 0)
    n = x.shape[0]
    out = np.zeros_like(x)
    pos = np.arange(n)
    for i, fi in enumerate(f):
        tap = i - R
        out += fi * x[reflect_index(pos - tap, n)]
    return np.moveaxis(out, 0, axis)


def conv_axis_stack(x: np.ndarray, f: np.ndarray, terms, axis: int) -> np.ndarray:
    """The stacked convolution of ops.conv_axis_stack: out[t] = sum over the terms (s, g) of t of
    conv_axis(x[s], f[g]) along axis (an axis of x other than the first, the slot axis)."""
    x = np.asarray(x, dtype=np.float64)
    f = np.atleast_2d(np.asarray(f, dtype=np.float64))
    ax = axis % x.ndim
    if ax == 0:
        raise ValueError("axis must not be the slot axis")
    return np.stack([sum(conv_axis(x[s], f[g], ax - 1) for s, g in t) for t in terms])


def resample_weights(n: int, q: int) -> np.ndarray:
    """The resampling matrix [N_out, n] (linear interpolation at n_out * p / q)."""
    p, q = rational_factor(q)
    n_out = resampled_length(n, q)
    M = np.zeros((n_out, n))
    for k in range(n_out):
        i0, r = divmod(k * p, q)
        M[k, i0] += 1.0 - r / q
        if r:
            M[k, i0 + 1] += r / q
    return M


def resample_axis(x: np.ndarray, q: int, axis: int) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    M = resample_weights(x.shape[axis], q)
    return np.moveaxis(np.tensordot(M, np.moveaxis(x, axis, 0), axes=(1, 0)), 0, axis)


def decompose_level(img: np.ndarray, q: int, filters=None) -> Dict[str, np.ndarray]:
    """One level of the reference transform of img [H, W, C] -> {band: [H', W', C]}."""
    f = design_filters(q) if filters is None else filters
    rows = {k: resample_axis(conv_axis(img, f[k], axis=1), q, axis=1) for k in ("h0", "h1", "g")}
    out = {}
    for band in BANDS:
        fr, fc = BAND_FILTERS[band]
        out[band] = resample_axis(conv_axis(rows[fr], f[fc], axis=0), q, axis=0)
    return out


def decompose(img: np.ndarray, q: int, levels: int = 2) -> List[Dict[str, np.ndarray]]:
    """J-level reference transform of img [H, W] or [H, W, C]; LL of level j feeds level j + 1."""
    img = np.asarray(img, dtype=np.float64)
    squeeze = img.ndim == 2
    if squeeze:
        img = img[:, :, None]
    f = design_filters(q)
    out = []
    cur = img
    for _ in range(levels):
        bands = decompose_level(cur, q, f)
        out.append({k: (v[:, :, 0] if squeeze else v) for k, v in bands.items()})
        cur = bands["LL"]
    return out


def loss_reference(rendered: np.ndarray, target: np.ndarray, q: int, levels: int,
                   weights, mask: np.ndarray | None = None) -> float:
    """sum_j sum_x lambda_x mean((W_x^j(target) - W_x^j(rendered))^2), images [H, W, C]."""
    r = np.asarray(rendered, np.float64)
    t = np.asarray(target, np.float64)
    if mask is not None:
        r = r * mask[:, :, None]
        t = t * mask[:, :, None]
    cr, ct = decompose(r, q, levels), decompose(t, q, levels)
    total = 0.0
    for lr, lt in zip(cr, ct):
        for band, lam in zip(BANDS, weights):
            total += lam * float(np.mean((lt[band] - lr[band]) ** 2))
    return total
