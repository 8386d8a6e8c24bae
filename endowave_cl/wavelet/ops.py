"""OpenCL host ops of the rational-wavelet transform (kernels in cl/wavelet.cl).

Every op takes and returns C-contiguous float32 ``pyopencl.array.Array``s.  Conventions (filters,
border rule, resampler, band definitions) are those of :mod:`endowave_cl.wavelet.filters`.

Axis-generic ops run along one axis of an array of any rank:
  conv_axis / conv_axis_bwd           convolution with an odd-length filter, reflect border
  conv_axis_stack / _bwd              the same over a stack of arrays: each output slot a sum of
                                      convolutions of input slots with filters of a filter stack
  resample_axis / resample_axis_bwd   rational resampling by a = (q + 1) / q
  conv_resample_stack /               a stacked convolution then the resampling along one axis,
    resample_conv_stack_bwd           and its adjoint: one launch each for an image's rows
Image-level ops, images channel-last [H, W, C]:
  decompose_level_stack / _bwd          one level as a band stack [bands, H', W', C]: two stacked
                                        convolutions and two resamplings, whatever the bands
  decompose(rt, img, q, levels)         -> [{"LL","LH","HL","HH": [H_j, W_j, C]} for each level j]
  decompose_bwd(rt, v_coeffs, shape, q) -> v_img [H, W, C]   (the adjoint of decompose)
  loss_and_grad(rt, rendered, target, mask, q, levels, weights) -> (loss, v_rendered)
"""
from __future__ import annotations

from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from ..ops.rasterize import simt_device
from ..runtime import round_up, view
from .filters import BAND_FILTERS, BANDS, design_filters, rational_factor, resampled_length

KFILE = "wavelet.cl"
GROUP = 64            # 1-D work-group multiple for the element-wise kernels
RED_CHUNK = 64        # consecutive elements per work-item of sumsq_scale (a multiple of 8)


def _empty(rt, shape) -> cla.Array:
    return rt.empty(tuple(int(s) for s in shape), np.float32)


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
# (research/PERFORMANCE.md, sixth pass); 8 on GPUs, the setting measured there
CONV_RUN_CPU, CONV_RUN_GPU = 16, 8
RS_RUN = 8            # consecutive elements per work-item of resample_axis / resample_axis_bwd (RS_RUN there)
RS_ROW_POS = 8        # positions per work-item of resample_axis_rows / resample_axis_bwd_rows (RS_ROW_POS there)
ROWS_RANGE = 8        # multiple of the row resampling kernels' range along a line
# Row passes (a run spans positions: inner < CONV_RUN) stage their lines in local memory
# (conv_axis_rows, conv_axis_rows_bwd): their border runs are then plain vector runs (research/PERFORMANCE.md,
# fourteenth pass).  STAGED_ROWS = False: the unstaged kernels everywhere (tests compare the two).
STAGED_ROWS = True
ROWS_GROUP_SIMT = 64    # work-items per line of the staged row passes on lock-step SIMD devices (GPUs);
                        # elsewhere one (CPU drivers: a work-group's barrier and work-item loops cost
                        # more than the line's runs share out, measured on PoCL)
ROWS_LOCAL_SHARE = 0.5  # at most this share of the device's local memory for the staged lines


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


def _filter_stack(rt, f) -> Tuple[cla.Array, int, int]:
    """(device filters, count, flen) of one filter [flen] or a stack [count, flen] (numpy or device)."""
    if isinstance(f, cla.Array):
        arr = f
    else:
        f = np.asarray(f, dtype=np.float32)
        arr = cla.to_device(rt.queue, np.ascontiguousarray(f))
    count, flen = (1, int(arr.size)) if arr.ndim == 1 else (int(arr.shape[0]), int(arr.shape[-1]))
    if arr.ndim > 2 or flen % 2 != 1:
        raise ValueError(f"filter length must be odd, got {flen}")
    return arr, count, flen


FILTERS = ("h0", "h1", "g")   # the order of device_filter_stack's rows


def device_filter_stack(rt, q: int) -> cla.Array:
    """h0, h1, g of design_filters(q) as a float32 device stack [3, flen] (cached per runtime and q)."""
    def make():
        f = design_filters(q)
        return cla.to_device(rt.queue, np.stack([f[k] for k in FILTERS]).astype(np.float32))
    return rt.cached(("wavelet.filters", int(q)), make)


Terms = Tuple[Tuple[Tuple[int, int], ...], ...]   # per output slot: ((input slot, filter index), ...)


def _terms_table(rt, terms: Terms, n_in: int, n_filters: int) -> Tuple[cla.Array, int]:
    """The term table of cl/wavelet.cl conv_axis (count, then (slot, filter) pairs per output slot),
    cached per runtime, and its row stride."""
    terms = tuple(tuple((int(s), int(g)) for s, g in t) for t in terms)
    for t in terms:
        if not t or any(not (0 <= s < n_in and 0 <= g < n_filters) for s, g in t):
            raise ValueError(f"terms {t} need 1 or more (slot < {n_in}, filter < {n_filters}) pairs")

    def make():
        stride = 1 + 2 * max(len(t) for t in terms)
        table = np.zeros((len(terms), stride), np.int32)
        for i, t in enumerate(terms):
            table[i, 0] = len(t)
            table[i, 1:1 + 2 * len(t)] = np.asarray(t, np.int32).ravel()
        return cla.to_device(rt.queue, table.ravel()), stride
    return rt.cached(("wavelet.terms", terms), make)


SINGLE: Terms = (((0, 0),),)   # one output slot: input slot 0 with filter 0


# ---------------------------------------------------------------------------------------------
# axis-generic ops
# ---------------------------------------------------------------------------------------------

BORDERS = ("reflect", "zero")


def _stack_axis(x: cla.Array, axis: int) -> Tuple[int, int, int, int]:
    """(slots, outer, n, inner) of a stack x [slots, ...] around axis (an axis of x, not the first)."""
    ax = axis % x.ndim
    if x.ndim < 2 or ax == 0:
        raise ValueError(f"axis {axis} of a stack {x.shape} must not be its first (the slot) axis")
    outer, n, inner = _dims(x.shape[1:], ax - 1)
    return int(x.shape[0]), outer, n, inner


def _conv_stack(rt, kname: str, x: cla.Array, f, terms: Terms, axis: int, out: Optional[cla.Array],
                flag: bool) -> cla.Array:
    """One launch of cl/wavelet.cl conv_axis or conv_axis_bwd over the stack x (flag: the zero
    border of the one, accumulate of the other)."""
    farr, nf, flen = _filter_stack(rt, f)
    slots, outer, n, inner = _stack_axis(x, axis)
    table, stride = _terms_table(rt, terms, slots, nf)
    shape = (len(terms),) + tuple(x.shape[1:])
    out = _empty(rt, shape) if out is None else out
    if tuple(out.shape) != shape:
        raise ValueError(f"out must be {shape}, got {out.shape}")
    run = conv_run(rt)
    args = (x.data, out.data, farr.data, np.int32(flen), np.int32(outer), np.int32(n), np.int32(inner),
            np.int32(bool(flag)), table.data, np.int32(stride))
    staged = _staged_rows_floats(rt, kname, n, inner, flen, max(len(t) for t in terms), run)
    if staged:   # a row pass: one work-group per line, its input lines staged in local memory
        group = rows_group(rt)
        rt.launch(rt.kernel(KFILE, kname.replace("conv_axis", "conv_axis_rows"), [f"-DCONV_RUN={run}"]),
                  (group, max(outer, 1), len(terms)), (group, 1, 1), *args, cl.LocalMemory(4 * staged))
        return out
    items = -(-max(n * inner, 1) // run)
    rt.launch(rt.kernel(KFILE, kname, [f"-DCONV_RUN={run}"]),
              (round_up(items, GROUP), max(outer, 1), len(terms)), None, *args)
    return out


def rows_group(rt) -> int:
    """Work-items per line (one work-group) of the staged row passes on rt's device."""
    return min(ROWS_GROUP_SIMT, rt.max_work_group_size) if simt_device(rt) else 1


def _staged_rows_floats(rt, kname: str, n: int, inner: int, flen: int, nterm: int, run: int) -> int:
    """Floats of local memory conv_axis_rows / conv_axis_rows_bwd (cl/wavelet.cl) stage for one line,
    or 0 where the pass takes the unstaged kernel: where its runs stay within one position
    (inner >= run: the column passes, whose border runs are whole vectors already), for an adjoint
    line not longer than the filter (repeated reflections), or where the lines do not fit in
    ROWS_LOCAL_SHARE of the device's local memory."""
    if not STAGED_ROWS or inner >= run:
        return 0
    R = flen // 2
    if kname == "conv_axis_bwd" and n <= 2 * R + 1:
        return 0
    pad = 2 * R if kname == "conv_axis_bwd" else R
    floats = nterm * (n + 2 * pad) * inner + 1
    return floats if 4 * floats <= ROWS_LOCAL_SHARE * rt.local_mem_size else 0


def conv_axis_stack(rt, x: cla.Array, f, terms: Terms, axis: int, out: Optional[cla.Array] = None,
                    border: str = "reflect") -> cla.Array:
    """out[t] = sum over the terms (s, g) of t of the convolution of x[s] with f[g] along axis.

    x: a stack [S, ...]; f: filters [F, flen] (or one [flen]); terms: per output slot, (input slot,
    filter index) pairs, added in their order; axis: an axis of x other than the first.  Returns
    out [len(terms), ...].  border as conv_axis.  One launch for all the output slots."""
    _check(x, "x")
    if border not in BORDERS:
        raise ValueError(f"border must be one of {BORDERS}, got {border!r}")
    return _conv_stack(rt, "conv_axis", x, f, terms, axis, out, border == "zero")


def conv_axis_stack_bwd(rt, v_out: cla.Array, f, terms: Terms, axis: int, out: Optional[cla.Array] = None,
                        accumulate: bool = False) -> cla.Array:
    """Adjoint of conv_axis_stack with the same terms, read the other way: out[t] (+)= sum over the
    terms (s, g) of t of the adjoint of convolving with f[g], applied to v_out[s] (reflect border)."""
    _check(v_out, "v_out")
    if out is None and accumulate:
        raise ValueError("accumulate needs out")
    return _conv_stack(rt, "conv_axis_bwd", v_out, f, terms, axis, out, accumulate)


def _one(x: Optional[cla.Array]) -> Optional[cla.Array]:
    """x as a stack of one slot (a view)."""
    return None if x is None else view(x, (1,) + tuple(x.shape))


def conv_axis(rt, x: cla.Array, f, axis: int, out: Optional[cla.Array] = None,
              border: str = "reflect") -> cla.Array:
    """Convolution of x with the odd-length filter f along axis; same shape.  border "reflect"
    (whole-sample symmetric, the wavelet's rule) or "zero" (zero padding; its adjoint is the
    convolution with the reversed filter and the same border)."""
    _check(x, "x")
    if _filter_stack(rt, f)[1] != 1:
        raise ValueError("conv_axis takes one filter")
    out = _empty(rt, x.shape) if out is None else out
    conv_axis_stack(rt, _one(x), f, SINGLE, (axis % max(x.ndim, 1)) + 1, out=_one(out), border=border)
    return out


def conv_axis_bwd(rt, v_out: cla.Array, f, axis: int, out: Optional[cla.Array] = None,
                accumulate: bool = False) -> cla.Array:
    """Adjoint of conv_axis; adds into out when accumulate."""
    _check(v_out, "v_out")
    if out is None:
        if accumulate:
            raise ValueError("accumulate needs out")
        out = _empty(rt, v_out.shape)
    conv_axis_stack_bwd(rt, _one(v_out), f, SINGLE, (axis % max(v_out.ndim, 1)) + 1, out=_one(out),
                        accumulate=accumulate)
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
    if inner < RS_RUN:   # short inner axis (an image's rows): RS_ROW_POS positions per work-item
        rt.launch(rt.kernel(KFILE, "resample_axis_rows", _resample_options(q)),
                  (round_up(-(-max(n_out, 1) // RS_ROW_POS), ROWS_RANGE), max(outer, 1)), None, x.data, out.data,
                  np.int32(outer),
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
    if inner < RS_RUN:   # short inner axis (an image's rows): RS_ROW_POS positions per work-item
        rt.launch(rt.kernel(KFILE, "resample_axis_bwd_rows", _resample_options(q)),
                  (round_up(-(-max(int(n_in), 1) // RS_ROW_POS), ROWS_RANGE), max(outer, 1)), None,
                  v_out.data, out.data,
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
        return view(img, (img.shape[0], img.shape[1], 1))
    if img.ndim != 3:
        raise ValueError(f"image must be [H, W] or [H, W, C], got {img.shape}")
    return img


class LevelPlan:
    """Which bands one level computes (a subset of BANDS, in BANDS order: LL first when present, so
    that a stack's slot 0 is the next level's input) and the term tables of its four stacked
    convolutions.  rows: the row filters those bands need, in FILTERS order (the row stack's slots)."""

    def __init__(self, bands: Sequence[str]):
        self.bands = tuple(b for b in BANDS if b in bands)
        if not self.bands:
            raise ValueError("a level needs at least one band")
        self.rows = tuple(k for k in FILTERS if any(BAND_FILTERS[b][0] == k for b in self.bands))
        fi = FILTERS.index
        # forward: row slot r = the image (slot 0) with filter rows[r]; band slot i = its row slot with
        # its column filter
        self.row_terms: Terms = tuple(((0, fi(k)),) for k in self.rows)
        self.col_terms: Terms = tuple(((self.rows.index(BAND_FILTERS[b][0]), fi(BAND_FILTERS[b][1])),)
                                      for b in self.bands)
        # adjoint: row slot r gathers the bands made from it; the image gathers the row slots
        self.col_bwd_terms: Terms = tuple(
            tuple((i, fi(BAND_FILTERS[b][1])) for i, b in enumerate(self.bands) if BAND_FILTERS[b][0] == k)
            for k in self.rows)
        self.row_bwd_terms: Terms = (tuple((r, fi(k)) for r, k in enumerate(self.rows)),)


ALL_BANDS = LevelPlan(BANDS)


def decompose_level_stack(rt, img: cla.Array, q: int, plan: LevelPlan = ALL_BANDS) -> cla.Array:
    """One level: img [H, W, C] -> the band stack [len(plan.bands), H', W', C]."""
    f = device_filter_stack(rt, q)
    rows = conv_resample_stack(rt, _one(img), f, plan.row_terms, q, axis=2)   # [rows, H, W', C]
    cols = conv_axis_stack(rt, rows, f, plan.col_terms, axis=1)           # [bands, H, W', C]
    return resample_axis(rt, cols, q, axis=1)                             # [bands, H', W', C]


def decompose_level_stack_bwd(rt, v_stack: cla.Array, shape, q: int, plan: LevelPlan = ALL_BANDS,
                              out: Optional[cla.Array] = None, accumulate: bool = False) -> cla.Array:
    """Adjoint of decompose_level_stack: v_stack [bands, H', W', C] -> v_img [H, W, C] (added to out
    when accumulate)."""
    f = device_filter_stack(rt, q)
    H, W, C = (int(s) for s in shape)
    if out is None:
        if accumulate:
            raise ValueError("accumulate needs out")
        out = _empty(rt, (H, W, C))
    u = resample_axis_bwd(rt, v_stack, q, axis=1, n_in=H)                 # [bands, H, W', C]
    v_rows = conv_axis_stack_bwd(rt, u, f, plan.col_bwd_terms, axis=1)    # [rows, H, W', C]
    resample_conv_stack_bwd(rt, v_rows, q, W, f, plan.row_bwd_terms, axis=2, out=_one(out), accumulate=accumulate)
    return out


def conv_resample_stack(rt, x: cla.Array, f, terms: Terms, q: int, axis: int) -> cla.Array:
    """resample_axis(conv_axis_stack(x, f, terms, axis), q, axis) (reflect border): a pass's
    convolution and resampling along axis.  A row pass that conv_axis_rows stages runs as one launch
    (cl/wavelet.cl conv_resample_rows: the convolved line kept in local memory; the same bits as
    the two launches)."""
    _check(x, "x")
    farr, nf, flen = _filter_stack(rt, f)
    slots, outer, n, inner = _stack_axis(x, axis)
    run = conv_run(rt)
    staged = _staged_rows_floats(rt, "conv_axis", n, inner, flen, max(len(t) for t in terms), run)
    if not staged or 4 * (staged + n * inner) > ROWS_LOCAL_SHARE * rt.local_mem_size:
        return resample_axis(rt, conv_axis_stack(rt, x, f, terms, axis), q, axis=axis)
    table, stride = _terms_table(rt, terms, slots, nf)
    n_out = resampled_length(n, int(q))
    shape = list(x.shape)
    shape[0], shape[axis] = len(terms), n_out
    out = _empty(rt, shape)
    group = rows_group(rt)
    kernel = rt.kernel(KFILE, "conv_resample_rows", _resample_options(q) + [f"-DCONV_RUN={run}"])
    rt.launch(kernel, (group, max(outer, 1), len(terms)), (group, 1, 1), x.data, out.data, farr.data,
              np.int32(flen), np.int32(outer), np.int32(n), np.int32(n_out), np.int32(inner), table.data,
              np.int32(stride),
              cl.LocalMemory(4 * staged), cl.LocalMemory(4 * n * inner))
    return out


def resample_conv_stack_bwd(rt, v_out: cla.Array, q: int, n_in: int, f, terms: Terms, axis: int, out: cla.Array,
                            accumulate: bool = False) -> cla.Array:
    """conv_axis_stack_bwd(resample_axis_bwd(v_out, q, axis, n_in), f, terms, axis): the adjoint of
    a pass's convolution and resampling along axis, into out (+= with accumulate).  A row pass
    that conv_axis_rows_bwd stages runs as one launch (cl/wavelet.cl resample_conv_rows_bwd: the
    staged lines made by the resampling's adjoint; the same bits as the two launches)."""
    _check(v_out, "v_out")
    farr, nf, flen = _filter_stack(rt, f)
    slots, outer, n_out, inner = _stack_axis(v_out, axis)
    run = conv_run(rt)
    staged = _staged_rows_floats(rt, "conv_axis_bwd", int(n_in), inner, flen, max(len(t) for t in terms), run)
    if not staged or resampled_length(int(n_in), int(q)) != n_out:
        w = resample_axis_bwd(rt, v_out, q, axis=axis, n_in=n_in)
        return conv_axis_stack_bwd(rt, w, f, terms, axis, out=out, accumulate=accumulate)
    table, stride = _terms_table(rt, terms, slots, nf)
    shape = list(v_out.shape)
    shape[0], shape[axis] = len(terms), int(n_in)
    if tuple(out.shape) != tuple(shape):
        raise ValueError(f"out must be {tuple(shape)}, got {out.shape}")
    group = rows_group(rt)
    kernel = rt.kernel(KFILE, "resample_conv_rows_bwd", _resample_options(q) + [f"-DCONV_RUN={run}"])
    rt.launch(kernel, (group, max(outer, 1), len(terms)), (group, 1, 1), v_out.data, out.data, farr.data,
              np.int32(flen), np.int32(outer), np.int32(n_in), np.int32(n_out), np.int32(inner),
              np.int32(bool(accumulate)),
              table.data, np.int32(stride), cl.LocalMemory(4 * staged))
    return out


def _bands_of(stack: cla.Array, plan: LevelPlan) -> Dict[str, cla.Array]:
    return {b: stack[i] for i, b in enumerate(plan.bands)}


def decompose(rt, img: cla.Array, q: int, levels: int = 2) -> List[Dict[str, cla.Array]]:
    """J-level transform of img [H, W, C] (or [H, W]); LL of level j is the input of level j + 1.
    Each level's bands are views of its band stack."""
    _check(img, "img")
    cur = _as_hwc(img)
    out = []
    for _ in range(int(levels)):
        stack = decompose_level_stack(rt, cur, q)
        out.append(_bands_of(stack, ALL_BANDS))
        cur = stack[0]
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
    stacks = []   # the cotangents copied into band stacks [4, H_j, W_j, C]
    for j, vb in enumerate(v_coeffs):
        stack = _empty(rt, (len(BANDS), resampled_length(shapes[j][0], q), resampled_length(shapes[j][1], q), C))
        nbytes = stack[0].nbytes
        for i, b in enumerate(BANDS):
            v = vb[b]
            _check(v, f"v_coeffs[{j}][{b!r}]")
            if v.nbytes != nbytes:
                raise ValueError(f"v_coeffs[{j}][{b!r}] has {v.size} values, the band {stack.shape[1:]}")
            cl.enqueue_copy(rt.queue, stack.base_data, v.base_data, dst_offset=i * nbytes, src_offset=v.offset,
                            byte_count=nbytes)
        stacks.append(stack)
    # each level's adjoint adds into the LL slot of the level above, then runs that level's
    for j in range(len(stacks) - 1, 0, -1):
        decompose_level_stack_bwd(rt, stacks[j], (shapes[j][0], shapes[j][1], C), q, out=stacks[j - 1][0],
                                  accumulate=True)
    return decompose_level_stack_bwd(rt, stacks[0], (H, W, C), q)


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

    partial: the device partial sums (float32) the loss is made of; finish(host copy of
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
    return partial, finish, view(v, rendered.shape)


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
    # a band is computed only where it counts: a weight, or LL feeding the next level
    plans = [LevelPlan([b for i, b in enumerate(BANDS) if lam[i] != 0 or (b == "LL" and j < levels - 1)])
             for j in range(int(levels))] if any(lam) else []
    if not plans:
        partial = _empty(rt, (1,))
        partial.fill(0)
        v = _empty(rt, (H, W, C))
        v.fill(0)
        return partial, lambda host_partial: 0.0, v
    stacks, cur = [], _as_hwc(d)
    for plan in plans:
        stacks.append(decompose_level_stack(rt, cur, q, plan))
        cur = stacks[-1][0]
    red = rt.kernel(KFILE, "sumsq_scale", [f"-DRED_CHUNK={RED_CHUNK}"])
    chunks = [-(-int(st[0].size) // RED_CHUNK) for st in stacks]
    partial = _empty(rt, (sum(c * len(p.bands) for c, p in zip(chunks, plans)),))
    terms = []   # (lambda, band size, first partial sum, partial sums) per band
    for plan, stack, nc in zip(plans, stacks, chunks):
        m, base = int(stack[0].size), sum(t[3] for t in terms)
        # the band's squares summed, and the band made its cotangent in place: 2 lambda / n * coefficient
        scales = [2.0 * lam[BANDS.index(b)] / m for b in plan.bands] + [0.0] * (4 - len(plan.bands))
        rt.launch(red, (nc, len(plan.bands)), None, stack.data, np.int32(m), partial.data, np.int32(base),
                  *(np.float32(x) for x in scales))
        terms += [(lam[BANDS.index(b)], m, base + i * nc, nc) for i, b in enumerate(plan.bands)]
    for j in range(len(plans) - 1, 0, -1):     # adds into the LL slot of the level above
        sh = stacks[j - 1].shape
        decompose_level_stack_bwd(rt, stacks[j], sh[1:], q, plans[j], out=stacks[j - 1][0], accumulate=True)
    v = decompose_level_stack_bwd(rt, stacks[0], (H, W, C), q, plans[0])

    def finish(host_partial: np.ndarray) -> float:
        host = np.asarray(host_partial).astype(np.float64)
        loss = 0.0
        for lam_b, n, first, count in terms:
            loss += lam_b * host[first:first + count].sum() / n
        return float(loss)

    return partial, finish, v
