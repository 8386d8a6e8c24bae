"""OpenCL host ops of the rational-wavelet transform (kernels in cl/wavelet.cl).

Every op takes and returns C-contiguous float32 ``pyopencl.array.Array``s.  Conventions (filters,
border rule, resampler, band definitions) are those of :mod:`endowave_cl.wavelet.filters`.

Axis-generic ops run along one axis of an array of any rank:
  conv_axis / conv_axis_bwd           convolution with an odd-length filter, reflect border
  resample_axis / resample_axis_bwd   rational resampling by a = (q + 1) / q
Image-level ops, images channel-last [H, W, C]:
  decompose(rt, img, q, levels)         -> [{"LL","LH","HL","HH": [H_j, W_j, C]} for each level j]
  decompose_bwd(rt, v_coeffs, shape, q) -> v_img [H, W, C]   (the adjoint of decompose)
  loss_and_grad(rt, rendered, target, mask, q, levels, weights) -> (loss, v_rendered)
"""
from __future__ import annotations

from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from ..runtime import round_up
from .filters import BAND_FILTERS, BANDS, design_filters, rational_factor, resampled_length

KFILE = "wavelet.cl"
GROUP = 64            # 1-D work-group multiple for the element-wise kernels
RED_LOCAL = 64        # work-items per group in sumsq_partial (power of two)
RED_GROUPS = 64       # groups per sumsq_partial launch (one slot = RED_GROUPS partial sums)


def _empty(rt, shape) -> cla.Array:
    return cla.empty(rt.queue, tuple(int(s) for s in shape), np.float32, allocator=rt.pool())


def _check(x: cla.Array, name: str) -> None:
    if x.dtype != np.float32 or not x.flags.c_contiguous:
        raise TypeError(f"{name} must be a C-contiguous float32 pyopencl array, got {x.dtype}")


def _dims(shape, axis: int) -> Tuple[int, int, int]:
    """(outer, n, inner) view of shape around axis."""
    axis = axis % len(shape)
    outer = int(np.prod(shape[:axis], dtype=np.int64))
    inner = int(np.prod(shape[axis + 1:], dtype=np.int64))
    return outer, int(shape[axis]), inner


def _launch(rt, kernel, total: int, *args) -> None:
    """1-D range over total elements (element-wise kernels)."""
    rt.launch(kernel, (round_up(max(int(total), 1), GROUP),), None, *args)


# consecutive elements per work-item of conv_axis / conv_axis_bwd (CONV_RUN in cl/wavelet.cl): 16 on
# CPUs, where twice the run halves the work-items and each tap feeds two 8-wide vectors
# (docs/PERFORMANCE.md, sixth pass); 8 on GPUs, the setting measured there
CONV_RUN_CPU, CONV_RUN_GPU = 16, 8
RS_RUN = 8            # consecutive elements per work-item of resample_axis / resample_axis_bwd (RS_RUN there)


def conv_run(rt) -> int:
    """Elements per work-item of the convolution kernels on rt's device."""
    return CONV_RUN_GPU if rt.is_gpu else CONV_RUN_CPU


def _launch_axis(rt, kernel, n: int, inner: int, outer: int, *args, run: int = 1) -> None:
    """2-D range of the axis kernels: (ceil(n * inner / run) rounded up, outer); a work-item
    computes `run` consecutive elements of a line."""
    items = -(-max(int(n) * int(inner), 1) // run)
    rt.launch(kernel, (round_up(items, GROUP), max(int(outer), 1)), None, *args)


def _resample_options(q: int) -> List[str]:
    """Build options of the resampling kernels: the factor a = p / q as constants RP, RQ."""
    p, q = rational_factor(q)
    return [f"-DRP={p}", f"-DRQ={q}"]


def _filter_array(rt, f) -> Tuple[cla.Array, int]:
    if isinstance(f, cla.Array):
        n = int(f.size)
        arr = f
    else:
        f = np.ascontiguousarray(np.asarray(f, dtype=np.float32).ravel())
        n = int(f.size)
        arr = cla.to_device(rt.queue, f)
    if n % 2 != 1:
        raise ValueError(f"filter length must be odd, got {n}")
    return arr, n


def device_filters(rt, q: int) -> Dict[str, cla.Array]:
    """h0, h1, g of design_filters(q) as float32 device arrays (cached per runtime and q)."""
    return rt.cached(("wavelet.filters", int(q)), lambda: {
        k: cla.to_device(rt.queue, v.astype(np.float32)) for k, v in design_filters(q).items()})


# ---------------------------------------------------------------------------------------------
# axis-generic ops
# ---------------------------------------------------------------------------------------------

BORDERS = ("reflect", "zero")


def conv_axis(rt, x: cla.Array, f, axis: int, out: Optional[cla.Array] = None,
              border: str = "reflect") -> cla.Array:
    """Convolution of x with the odd-length filter f along axis; same shape.  border "reflect"
    (whole-sample symmetric, the wavelet's rule) or "zero" (zero padding; its adjoint is the
    convolution with the reversed filter and the same border)."""
    _check(x, "x")
    if border not in BORDERS:
        raise ValueError(f"border must be one of {BORDERS}, got {border!r}")
    farr, flen = _filter_array(rt, f)
    outer, n, inner = _dims(x.shape, axis)
    out = _empty(rt, x.shape) if out is None else out
    run = conv_run(rt)
    _launch_axis(rt, rt.kernel(KFILE, "conv_axis", [f"-DCONV_RUN={run}"]), n, inner, outer, x.data, out.data,
                 farr.data, np.int32(flen), np.int32(outer), np.int32(n), np.int32(inner),
                 np.int32(border == "zero"), run=run)
    return out


def conv_axis_bwd(rt, v_out: cla.Array, f, axis: int, out: Optional[cla.Array] = None,
                accumulate: bool = False) -> cla.Array:
    """Adjoint of conv_axis; adds into out when accumulate."""
    _check(v_out, "v_out")
    farr, flen = _filter_array(rt, f)
    outer, n, inner = _dims(v_out.shape, axis)
    if out is None:
        if accumulate:
            raise ValueError("accumulate needs out")
        out = _empty(rt, v_out.shape)
    run = conv_run(rt)
    _launch_axis(rt, rt.kernel(KFILE, "conv_axis_bwd", [f"-DCONV_RUN={run}"]), n, inner, outer, v_out.data,
                 out.data, farr.data, np.int32(flen), np.int32(outer), np.int32(n), np.int32(inner),
                 np.int32(bool(accumulate)), run=run)
    return out


def resample_axis(rt, x: cla.Array, q: int, axis: int, out: Optional[cla.Array] = None) -> cla.Array:
    """Resample x along axis by a = (q + 1) / q; that axis becomes resampled_length(n, q) long."""
    _check(x, "x")
    q = int(q)
    outer, n, inner = _dims(x.shape, axis)
    n_out = resampled_length(n, q)
    shape = list(x.shape)
    shape[axis % len(shape)] = n_out
    out = _empty(rt, shape) if out is None else out
    if inner < RS_RUN:   # short inner axis (an image's rows): one work-item per position
        rt.launch(rt.kernel(KFILE, "resample_axis_rows", _resample_options(q)),
                  (round_up(max(n_out, 1), GROUP), max(outer, 1)), None, x.data, out.data, np.int32(outer),
                  np.int32(n), np.int32(n_out), np.int32(inner))
        return out
    _launch_axis(rt, rt.kernel(KFILE, "resample_axis", _resample_options(q)), n_out, inner, outer, x.data,
                 out.data, np.int32(outer), np.int32(n), np.int32(n_out), np.int32(inner), run=RS_RUN)
    return out


def resample_axis_bwd(rt, v_out: cla.Array, q: int, axis: int, n_in: int,
                    out: Optional[cla.Array] = None, accumulate: bool = False) -> cla.Array:
    """Adjoint of resample_axis (n_in: the input length along axis)."""
    _check(v_out, "v_out")
    q = int(q)
    outer, n_out, inner = _dims(v_out.shape, axis)
    if resampled_length(n_in, q) != n_out:
        raise ValueError(f"n_in={n_in} does not resample to {n_out} with q={q}")
    shape = list(v_out.shape)
    shape[axis % len(shape)] = int(n_in)
    if out is None:
        if accumulate:
            raise ValueError("accumulate needs out")
        out = _empty(rt, shape)
    if inner < RS_RUN:   # short inner axis (an image's rows): one work-item per position
        rt.launch(rt.kernel(KFILE, "resample_axis_bwd_rows", _resample_options(q)),
                  (round_up(max(int(n_in), 1), GROUP), max(outer, 1)), None, v_out.data, out.data,
                  np.int32(outer), np.int32(n_in), np.int32(n_out), np.int32(inner), np.int32(bool(accumulate)))
        return out
    _launch_axis(rt, rt.kernel(KFILE, "resample_axis_bwd", _resample_options(q)), n_in, inner, outer, v_out.data,
                 out.data, np.int32(outer), np.int32(n_in), np.int32(n_out), np.int32(inner),
                 np.int32(bool(accumulate)), run=RS_RUN)
    return out


# ---------------------------------------------------------------------------------------------
# the J-level transform and its adjoint
# ---------------------------------------------------------------------------------------------

def _as_hwc(img: cla.Array) -> cla.Array:
    if img.ndim == 2:
        return img.reshape(img.shape[0], img.shape[1], 1)
    if img.ndim != 3:
        raise ValueError(f"image must be [H, W] or [H, W, C], got {img.shape}")
    return img


def decompose_level(rt, img: cla.Array, q: int) -> Dict[str, cla.Array]:
    """One level: img [H, W, C] -> {band: [H', W', C]}."""
    f = device_filters(rt, q)
    H, W, C = img.shape
    rows = {}
    tmp = _empty(rt, (H, W, C))
    for k in ("h0", "h1", "g"):
        conv_axis(rt, img, f[k], axis=1, out=tmp)
        rows[k] = resample_axis(rt, tmp, q, axis=1)              # [H, W', C]
    W2 = rows["h0"].shape[1]
    tmp2 = _empty(rt, (H, W2, C))
    out = {}
    for band in BANDS:
        fr, fc = BAND_FILTERS[band]
        conv_axis(rt, rows[fr], f[fc], axis=0, out=tmp2)
        out[band] = resample_axis(rt, tmp2, q, axis=0)           # [H', W', C]
    return out


def decompose(rt, img: cla.Array, q: int, levels: int = 2) -> List[Dict[str, cla.Array]]:
    """J-level transform of img [H, W, C] (or [H, W]); LL of level j is the input of level j + 1."""
    _check(img, "img")
    cur = _as_hwc(img)
    out = []
    for _ in range(int(levels)):
        bands = decompose_level(rt, cur, q)
        out.append(bands)
        cur = bands["LL"]
    return out


def decompose_level_bwd(rt, v_bands: Dict[str, Sequence[cla.Array]], shape, q: int,
                      out: Optional[cla.Array] = None, accumulate: bool = False) -> cla.Array:
    """Adjoint of decompose_level.  v_bands maps each band to a list of cotangents [H', W', C]
    that are summed (so LL can take its own cotangent and the next level's adjoint)."""
    f = device_filters(rt, q)
    H, W, C = (int(s) for s in shape)
    W2 = resampled_length(W, q)
    tmp = _empty(rt, (H, W2, C))
    v_rows = {}
    for band in BANDS:
        fr, fc = BAND_FILTERS[band]
        parts = [v for v in v_bands[band] if v is not None]
        for i, v in enumerate(parts):
            resample_axis_bwd(rt, v, q, axis=0, n_in=H, out=tmp, accumulate=i > 0)
        if not parts:
            continue
        acc = fr in v_rows
        if not acc:
            v_rows[fr] = _empty(rt, (H, W2, C))
        conv_axis_bwd(rt, tmp, f[fc], axis=0, out=v_rows[fr], accumulate=acc)
    if out is None:
        if accumulate:
            raise ValueError("accumulate needs out")
        out = _empty(rt, (H, W, C))
    tmp_w = _empty(rt, (H, W, C))
    first = not accumulate
    if not v_rows:
        if first:
            out.fill(0)
        return out
    for k, v in v_rows.items():
        resample_axis_bwd(rt, v, q, axis=1, n_in=W, out=tmp_w)
        conv_axis_bwd(rt, tmp_w, f[k], axis=1, out=out, accumulate=not first)
        first = False
    return out


def decompose_bwd(rt, v_coeffs: List[Dict[str, cla.Array]], shape, q: int) -> cla.Array:
    """Adjoint of decompose: cotangents of every band of every level -> v_img [H, W, C]."""
    shape = tuple(int(s) for s in shape)
    if len(shape) == 2:
        shape = shape + (1,)
    H, W, C = shape
    shapes = [(H, W)]
    for _ in range(len(v_coeffs) - 1):
        shapes.append((resampled_length(shapes[-1][0], q), resampled_length(shapes[-1][1], q)))
    v_next = None
    for j in range(len(v_coeffs) - 1, -1, -1):
        vb = {b: [v_coeffs[j][b]] for b in BANDS}
        vb["LL"].append(v_next)
        v_next = decompose_level_bwd(rt, vb, (shapes[j][0], shapes[j][1], C), q)
    return v_next


# ---------------------------------------------------------------------------------------------
# the loss
# ---------------------------------------------------------------------------------------------

def loss_and_grad(rt, rendered: cla.Array, target: cla.Array, mask: Optional[cla.Array],
                  q: int, levels: int, weights: Sequence[float]) -> Tuple[float, cla.Array]:
    """L = sum_j sum_x lambda_x mean_{band}((W_x^j(m t) - W_x^j(m r))^2) and dL/d rendered.

    The transform is linear, so it runs once on d = m (r - t); the gradient is
    m * W^T(2 lambda_x / n_x * W_x d), n_x = the number of coefficients of the band (H_j W_j C).
    """
    partial, finish, v = loss_and_grad_deferred(rt, rendered, target, mask, q, levels, weights)
    return finish(partial.get()), v


def loss_and_grad_deferred(rt, rendered: cla.Array, target: cla.Array, mask: Optional[cla.Array],
                           q: int, levels: int, weights: Sequence[float]):
    """loss_and_grad without its blocking read: (partial, finish, v_rendered).

    partial: the device sums [slots * RED_GROUPS] float32 the loss is made of; finish(host copy of
    partial) -> the loss (float).  The trainer reads partial back with the step's other scalars.
    """
    _check(rendered, "rendered")
    _check(target, "target")
    if rendered.shape != target.shape:
        raise ValueError(f"rendered {rendered.shape} and target {target.shape} differ")
    r3, t3 = _as_hwc(rendered), _as_hwc(target)
    H, W, C = r3.shape
    npix = H * W
    if mask is not None:
        _check(mask, "mask")
        if mask.size != npix:
            raise ValueError(f"mask must be [H, W] = {(H, W)}, got {mask.shape}")
    lam = [float(w) for w in weights]
    if len(lam) != 4:
        raise ValueError("weights must be the four lambdas (LL, LH, HL, HH)")
    has_mask = np.int32(mask is not None)
    mask_data = (mask if mask is not None else r3).data  # any valid buffer when there is no mask
    d = _empty(rt, (H, W, C))
    _launch(rt, rt.kernel(KFILE, "masked_diff"), npix * C, r3.data, t3.data, mask_data, d.data,
            np.int32(npix), np.int32(C), has_mask)
    partial, finish, v = diff_loss_and_grad_deferred(rt, d, q, levels, lam)
    if mask is not None:
        _launch(rt, rt.kernel(KFILE, "scale_masked"), v.size, v.data, mask.data, np.float32(1.0), np.int32(npix),
                np.int32(C), np.int32(1))
    return partial, finish, v.reshape(rendered.shape)


def diff_loss_and_grad_deferred(rt, d: cla.Array, q: int, levels: int, weights: Sequence[float]):
    """The wavelet loss of the masked difference d = m (r - t) [H, W, C] (made by the caller):
    (partial, finish, W^T(2 lambda_x / n_x * W_x d)) as loss_and_grad_deferred, but the returned
    cotangent is not yet multiplied by the mask (the caller folds m into its own use of it).
    d is only read."""
    _check(d, "d")
    H, W, C = _as_hwc(d).shape
    lam = [float(w) for w in weights]
    if len(lam) != 4:
        raise ValueError("weights must be the four lambdas (LL, LH, HL, HH)")
    coeffs = decompose(rt, _as_hwc(d), q, levels)
    slots = len(coeffs) * len(BANDS)
    partial = _empty(rt, (slots * RED_GROUPS,))
    local = min(RED_LOCAL, rt.max_work_group_size)
    local = 1 << (local.bit_length() - 1)
    red = rt.kernel(KFILE, "sumsq_partial")
    scl = rt.kernel(KFILE, "scale_masked")
    sizes = []
    for j, bands in enumerate(coeffs):
        for b, band in enumerate(BANDS):
            x = bands[band]
            slot = j * len(BANDS) + b
            rt.launch(red, (RED_GROUPS * local,), (local,), x.data, np.int32(x.size), partial.data,
                      np.int32(slot), cl.LocalMemory(4 * local))
            sizes.append(x.size)
            # cotangent of the band, in place: 2 lambda / n * coefficient
            _launch(rt, scl, x.size, x.data, x.data, np.float32(2.0 * lam[b] / x.size),
                    np.int32(x.size), np.int32(1), np.int32(0))
    v = decompose_bwd(rt, coeffs, (H, W, C), q)

    def finish(host_partial: np.ndarray) -> float:
        sums = np.asarray(host_partial).astype(np.float64).reshape(slots, RED_GROUPS).sum(axis=1)
        loss = 0.0
        for s_i, (sq, n) in enumerate(zip(sums, sizes)):
            loss += lam[s_i % len(BANDS)] * sq / n
        return float(loss)

    return partial, finish, v
