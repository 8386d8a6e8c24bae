"""Host ops of the tile rasterizer: forward, adjoint and densification statistics.

Kernels: cl/rasterize.cl, cl/rasterize_bwd.cl, cl/densify_stats.cl, and the explicit-SIMD
cl/rasterize_vec.cl, cl/rasterize_vec_bwd.cl for CPU drivers (see ``raster_variant``).  References (same names):
endowave_cl/reference/rasterize.py.  The compositing constants (ALPHA_MAX, ALPHA_MIN, T_STOP) come
from endowave_cl/layout.py and are passed to the kernels as build options, so both sides use the
same values.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import Dict

import numpy as np
import pyopencl.array as cla

from .. import env, probe
from ..errors import EndowaveError
from ..layout import TILE, tile_grid
from ..probe import ENV_PLANT
from ..runtime import ENV_CACHE_DIR
from .raster_options import RasterChoice, _options, vec_options  # noqa: F401  (re-exported)


# Kernel variants.  "scalar": one pixel per work-item (cl/rasterize.cl, rasterize_bwd.cl), the GPU
# path.  "vector": each work-item composites a block of VW pixels in floatVW lanes
# (cl/rasterize_vec.cl, cl/rasterize_vec_bwd.cl): CPU drivers such as PoCL do not vectorise the
# scalar kernel's per-pixel loop.  Same rules and results (to float rounding; `last` equal in the tests).
# On a CPU device the first use of a lane count is probed in a child process (endowave_cl/probe.py):
# VEC_WIDTHS are tried in order and the first that builds and matches the scalar kernel runs.
ENV_VARIANT = "ENDOWAVE_RASTER_VARIANT"     # scalar | vector: force a variant (tests, benchmarks)
ENV_VEC_WIDTH = "ENDOWAVE_RASTER_VW"        # force the lanes of the vector variant: 4, 8 or 16
VEC_WIDTH = 16                              # default lanes (fastest measured: PoCL, 2-core AVX2 x86)
VEC_WIDTHS = (16, 8, 4)                     # lane counts tried on a CPU device, fastest first
ENV_VEC_BLOCK_W = "ENDOWAVE_RASTER_BW"      # width of a work-item's pixel block (divides the lanes)
VEC_BLOCK_W = 4                             # default: 4 x 4 pixel blocks for 16 lanes (squarest: fewest
                                            # Gaussian-block pairs walked)
VARIANTS = ("scalar", "vector")


class RasterVariantError(EndowaveError):
    """A forced rasterizer variant failed its probe on this device."""


def _forced():
    bw = env.get(ENV_VEC_BLOCK_W)
    return env.get(ENV_VARIANT), env.get(ENV_VEC_WIDTH), None if bw is None else str(bw)


def raster_choice(rt, C: int = 6) -> RasterChoice:
    """The variant that runs on rt for C feature channels.

    $ENDOWAVE_RASTER_VARIANT / $ENDOWAVE_RASTER_VW force a variant / lane count; else GPUs run the
    scalar kernels (devices that report a SIMT width, DeviceCaps) and the others the vector ones at the first of VEC_WIDTHS whose probe passes
    (the Oclgrind simulator: VEC_WIDTH, not probed), then the scalar kernels.  A forced vector
    variant is probed too and raises RasterVariantError when its probe fails.  Falling back prints
    one line to stderr saying what runs and why."""
    forced_v, forced_w, forced_bw = _forced()
    key = ("raster_choice", int(C), forced_v, forced_w, forced_bw, env.raw(ENV_CACHE_DIR), env.raw(ENV_PLANT))
    ch = rt.cache.get(key)
    if ch is None:
        ch, notes, failed = explain_choice(rt, C)
        if ch is None:
            raise RasterVariantError(
                f"forced rasterizer variant on {rt.name} failed its probe ({'; '.join(failed)}); "
                f"unset {ENV_VARIANT} / {ENV_VEC_WIDTH} to let endowave-cl fall back")
        if failed:
            print(f"endowave-cl: {rt.name}: rasterizer runs the {ch.describe()} ({'; '.join(failed)}); "
                  f"verdicts in {probe.probe_dir()}, {ENV_VEC_WIDTH} / {ENV_VARIANT} force one",
                  file=sys.stderr, flush=True)
        rt.cache[key] = ch
    return ch


def explain_choice(rt, C: int = 6):
    """(choice, notes, failed): what raster_choice picks (None: a forced variant failed its probe),
    one note per variant considered ("16 lanes ok (2.1 s probe)", "GPU", "simulator, not probed",
    ...) and the notes of those that failed ("16 lanes: <what went wrong>")."""
    forced_v, forced_w, _ = _forced()
    if forced_v == "scalar":
        return RasterChoice("scalar"), [f"forced by {ENV_VARIANT}"], []
    if forced_v is None and forced_w is None and simt_device(rt):
        return RasterChoice("scalar"), [f"SIMT width {rt.caps.simt_width}"], []
    forced = bool(forced_v or forced_w)
    widths = (forced_w,) if forced_w else (VEC_WIDTH,) + tuple(w for w in VEC_WIDTHS if w < VEC_WIDTH)
    notes, failed = [], []
    for w in widths:
        try:
            bw = vec_block(w)[0]
        except ValueError as e:   # $ENDOWAVE_RASTER_BW does not suit this lane count
            if forced:
                raise
            failed.append(f"{w} lanes: {e}")
            notes.append(failed[-1])
            continue
        need = max(fwd_vec_local_bytes(C), vec_bwd_local_bytes(C, VEC_BWD_BATCHES[-1], w))
        if need > rt.local_mem_size:
            if forced:   # nothing to probe: rasterize says that it does not fit
                return RasterChoice("vector", w, bw), notes + [f"{w} lanes (too big for local memory)"], failed
            failed.append(f"{w} lanes: needs {need} bytes of local memory, the device has {rt.local_mem_size}")
            notes.append(failed[-1])
            continue
        if rt.is_oclgrind:   # a simulator: its builds cannot take the process down
            return RasterChoice("vector", w, bw), notes + [f"{w} lanes (simulator, not probed)"], failed
        v = probe.verdict(rt, C, w, bw)
        if v.ok:
            how = "cached verdict" if v.cached else f"{v.seconds:.1f} s probe"
            return RasterChoice("vector", w, bw), notes + [f"{w} lanes ok ({how})"], failed
        failed.append(f"{w} lanes: {v.reason}")
        notes.append(failed[-1])
    return (None if forced else RasterChoice("scalar")), notes, failed


def simt_device(rt) -> bool:
    """Whether rt's device runs work-items in lock-step hardware SIMD (DeviceCaps.simt: a warp,
    wavefront or sub-group width reported by the driver): the one-pixel-per-work-item kernels suit
    it; devices that report none (CPU drivers) run the explicit-SIMD vector kernels."""
    caps = getattr(rt, "caps", None)
    return bool(caps.simt) if caps is not None else bool(getattr(rt, "is_gpu", False))


def raster_variant(rt, C: int = 6) -> str:
    """"scalar" or "vector": the variant raster_choice picks for rt."""
    return raster_choice(rt, C).variant


def vec_width() -> int:
    """The forced lane count ($ENDOWAVE_RASTER_VW), else VEC_WIDTH."""
    return _forced()[1] or VEC_WIDTH


def vec_block(vw: int = None) -> tuple:
    """(BW, BH): a work-item's pixel block in the vector variant with vw lanes, BW * BH = vw."""
    vw = vw or vec_width()
    bw = env.get(ENV_VEC_BLOCK_W) or min(VEC_BLOCK_W, vw)
    if vw % bw or bw > TILE:
        raise env.EnvError(f"environment variable {ENV_VEC_BLOCK_W}={bw}: must divide the lane count {vw}")
    bh = vw // bw
    if TILE % bh:
        raise ValueError(f"block {bw} x {bh}: its {bh} rows must divide the tile's {TILE}")
    return bw, bh


def _vec_grid(width: int, height: int, ch: RasterChoice):
    """Global and local sizes of the vector kernels: (TILE / BW) x (TILE / BH) work-items per tile."""
    bw, bh = ch.bw, ch.vw // ch.bw
    tiles_x, tiles_y, _, _ = _grid(width, height)
    lsize = (TILE // bw, TILE // bh)
    return (tiles_x * lsize[0], tiles_y * lsize[1]), lsize


BWD_BATCH = 128   # Gaussians per local-memory batch of rasterize_bwd.cl (BATCH there)


def fwd_local_bytes(C: int) -> int:
    """Local memory of the rasterize kernel (mirror of its __local arrays)."""
    per_gaussian = 8 + 16 + 4 * C + 4 + 16 + 16      # mean, cop, feat, thr, box, 16 list slots
    return TILE * TILE * per_gaussian + 16 * 4 + 8


def fwd_vec_local_bytes(C: int) -> int:
    """Local memory of the rasterize_vec kernel (mirror of its __local arrays): the same for every
    lane count (each work-item keeps its batch's hit mask in private memory)."""
    per_gaussian = 8 + 16 + 4 * C + 4 + 16            # mean, cop, feat, thr, box
    return TILE * TILE * per_gaussian + 8


VEC_BWD_BATCHES = (64, 32, 16, 8)   # Gaussians per batch of rasterize_vec_bwd.cl, largest that fits first


def vec_bwd_local_bytes(C: int, batch: int, vw: int) -> int:
    """Local memory of the rasterize_vec_bwd kernel (mirror of its __local arrays)."""
    n_wi = (TILE // vw) * TILE
    nsv = (6 + C + 3) // 4                                           # float4 per slot (NSV)
    per_gaussian = 8 + 16 + 4 * C + 4 + 4 + 16 + 16 * nsv * n_wi  # mean, cop, feat, gid, thr, box, part
    return batch * per_gaussian + 4 * n_wi + 4                         # + wrote masks, max_last


def vec_bwd_batch(rt, C: int, vw: int) -> int:
    for batch in VEC_BWD_BATCHES:
        if vec_bwd_local_bytes(C, batch, vw) <= rt.local_mem_size:
            return batch
    return VEC_BWD_BATCHES[-1]   # too big: _check_local reports it


def bwd_local_bytes(C: int) -> int:
    """Local memory of the rasterize_bwd kernel (mirror of its __local arrays)."""
    nv = 6 + C
    per_gaussian = 8 + 16 + 4 * C + 4 + 4 + 4 + 1    # mean, cop, feat, gid, thr, mask, act
    return BWD_BATCH * per_gaussian + nv * (TILE * TILE + 16) * 4 + 8    # + l_pix, l_part


def _check_local(rt, need: int, what: str, C: int) -> None:
    if need > rt.local_mem_size:
        raise ValueError(f"{what} with C={C} feature channels needs {need} bytes of local memory; "
                         f"{rt.name} has {rt.local_mem_size}: use fewer channels")


@dataclass
class RasterOut:
    out: "object"      # [H, W, C] float32
    alpha: "object"    # [H, W] float32, 1 - T_final
    T_final: "object"  # [H, W] float32
    last: "object"     # [H, W] int32, one past the last contributor (relative to the tile's start)
    rec: "object" = None  # [N, REC4, 4] float32 records of the vector variant (reused by its adjoint)


def _buf(rt, arr):
    """arr's buffer, or the runtime's placeholder for empty/absent arrays (pyopencl gives empty
    ones no buffer)."""
    return rt.buf(arr)


def _grid(width: int, height: int):
    tiles_x, tiles_y = tile_grid(width, height)
    return tiles_x, tiles_y, (tiles_x * TILE, tiles_y * TILE), (TILE, TILE)


def _check(means2d, conic, opac, features, tile_ranges, width, height):
    N = features.shape[0]
    assert means2d.shape == (N, 2) and conic.shape == (N, 3) and opac.shape == (N,), \
        (means2d.shape, conic.shape, opac.shape, features.shape)
    tx, ty, _, _ = _grid(width, height)
    assert tile_ranges.shape == (tx * ty, 2), (tile_ranges.shape, tx * ty)
    for a in (means2d, conic, opac, features):
        assert a.dtype == np.float32 and a.flags.c_contiguous
    assert tile_ranges.dtype == np.int32


def rasterize(rt, means2d, conic, opac, features, sorted_values, tile_ranges, width: int,
              height: int, choice: RasterChoice = None) -> RasterOut:
    """Composite the sorted Gaussians front to back over a width x height image.

    means2d [N,2], conic [N,3], opac [N], features [N,C] float32; sorted_values [M] int32 (Gaussian
    ids, tile-major then depth); tile_ranges [n_tiles, 2] int32.  All pyopencl arrays.
    choice: the variant to run (default raster_choice(rt, C); the probe passes its own).
    """
    width, height = int(width), int(height)
    _check(means2d, conic, opac, features, tile_ranges, width, height)
    C = int(features.shape[1])
    res = RasterOut(rt.empty((height, width, C), np.float32),
                    rt.empty((height, width), np.float32),
                    rt.empty((height, width), np.float32),
                    rt.empty((height, width), np.int32))
    if width == 0 or height == 0:
        return res
    tiles_x, _, gsize, lsize = _grid(width, height)
    ch = choice or raster_choice(rt, C)
    if ch.variant == "vector":
        _check_local(rt, fwd_vec_local_bytes(C), "rasterize", C)
        opts = vec_options(C, ch)
        rec = _vec_records(rt, means2d, conic, opac, features, opts)
        k = rt.kernel("rasterize_vec.cl", "rasterize_vec", opts)
        gsize, lsize = _vec_grid(width, height, ch)
        rt.launch(k, gsize, lsize, _buf(rt, rec), _buf(rt, sorted_values), tile_ranges.data, np.int32(width),
                  np.int32(height), np.int32(tiles_x), res.out.data, res.alpha.data, res.T_final.data, res.last.data)
        res.rec = rec
        return res
    _check_local(rt, fwd_local_bytes(C), "rasterize", C)
    k = rt.kernel("rasterize.cl", "rasterize", _options(C))
    rt.launch(k, gsize, lsize, _buf(rt, means2d), _buf(rt, conic), _buf(rt, opac), _buf(rt, features),
              _buf(rt, sorted_values), tile_ranges.data, np.int32(width), np.int32(height), np.int32(tiles_x),
              res.out.data, res.alpha.data, res.T_final.data, res.last.data)
    return res


def vec_bwd_options(rt, C: int, ch: RasterChoice, det: bool):
    """Build options of rasterize_vec_bwd.cl."""
    return vec_options(C, ch) + [f"-DDETERMINISTIC={int(det)}", f"-DBATCH={vec_bwd_batch(rt, C, ch.vw)}"]


def _vec_records(rt, means2d, conic, opac, features, opts):
    """[N, REC4] float4 per-Gaussian records of the vector kernels (rasterize_vec_prep, REC4 in
    cl/rasterize_vec.cl), or None for N = 0."""
    N, C = (int(s) for s in features.shape)
    if N == 0:
        return None
    rec4 = 3 + (C + 3) // 4
    rec = rt.empty((N, rec4, 4), np.float32)
    kp = rt.kernel("rasterize_vec.cl", "rasterize_vec_prep", opts)
    wg = 64
    rt.launch_1d(kp, N, wg, means2d.data, conic.data, opac.data, features.data,
                 np.int32(N), rec.data)
    return rec


def rasterize_bwd(rt, means2d, conic, opac, features, sorted_values, tile_ranges, width: int,
                  height: int, raster_out: RasterOut, v_out, v_alpha, deterministic=None,
                  choice: RasterChoice = None) -> Dict[str, "object"]:
    """Adjoint of ``rasterize``: from v_out [H,W,C] and v_alpha [H,W] to
    dict(v_means2d [N,2], v_conic [N,3], v_opac [N], v_features [N,C]) (new pyopencl arrays).

    deterministic: None (default: per-group CAS adds, last-bit differences between runs) or a pair
    (rect [N,4] int32, offsets [N+1] int32), the rects and binning offsets the sorted list was built
    from (ops.binning.bin_gaussians): then the gradients are bit-identical from run to run
    (per-entry terms stored in sorted order, summed per Gaussian in its binning (tile) order through
    the slot -> entry map rasterize_bwd_entry_of builds from rect and offsets; needs M * (7 + C)
    words of scratch, M the length of sorted_values: ops.binning's capacity, at least the pairs).
    choice: the variant to run, as in ``rasterize``.
    """
    width, height = int(width), int(height)
    _check(means2d, conic, opac, features, tile_ranges, width, height)
    N, C = (int(s) for s in features.shape)
    assert v_out.shape == (height, width, C) and v_alpha.shape == (height, width)
    q, al = rt.queue, rt.pool()
    det = deterministic is not None
    M = int(sorted_values.shape[0])
    # the deterministic mode's gather writes every row (empty suffices) unless there is nothing
    # to gather; the atomic mode accumulates into zeros
    def zeros(shape, dtype):
        return cla.zeros(q, shape, dtype, allocator=al)
    make = rt.empty if det and M > 0 and width > 0 and height > 0 else zeros
    grads = {"v_means2d": make((N, 2), np.float32), "v_conic": make((N, 3), np.float32),
             "v_opac": make((N,), np.float32), "v_features": make((N, C), np.float32)}
    if N == 0 or width == 0 or height == 0:
        return grads
    tiles_x, _, gsize, lsize = _grid(width, height)
    if det and M == 0:
        return grads
    opts = _options(C) + [f"-DDETERMINISTIC={int(det)}"]
    # [M, NV] per sorted entry; the vector kernel writes every row (zeros past a tile's walk), the
    # scalar one only those it walks
    ch = choice or raster_choice(rt, C)
    if det:
        v_entry = (rt.empty if ch.variant == "vector" else zeros)((M, 6 + C), np.float32)
    else:
        v_entry = None
    rect, offsets = deterministic if det else (None, None)
    if det:
        assert rect.shape == (N, 4) and rect.dtype == np.int32, (rect.shape, rect.dtype)
        assert offsets.shape == (N + 1,) and offsets.dtype == np.int32, (offsets.shape, offsets.dtype)
    if ch.variant == "vector":
        batch = vec_bwd_batch(rt, C, ch.vw)
        _check_local(rt, vec_bwd_local_bytes(C, batch, ch.vw), "rasterize_bwd", C)
        rec = raster_out.rec
        if rec is None or rec.shape[0] != N:
            rec = _vec_records(rt, means2d, conic, opac, features, vec_options(C, ch))
        k = rt.kernel("rasterize_vec_bwd.cl", "rasterize_vec_bwd", vec_bwd_options(rt, C, ch, det))
        gsize, lsize = _vec_grid(width, height, ch)
        rt.launch(k, gsize, lsize, rec.data, _buf(rt, sorted_values), tile_ranges.data,
                  np.int32(width), np.int32(height), np.int32(tiles_x),
                  raster_out.T_final.data, raster_out.last.data, v_out.data, v_alpha.data,
                  grads["v_means2d"].data, grads["v_conic"].data, grads["v_opac"].data, grads["v_features"].data,
                  _buf(rt, v_entry))
    else:
        _check_local(rt, bwd_local_bytes(C), "rasterize_bwd", C)
        k = rt.kernel("rasterize_bwd.cl", "rasterize_bwd", opts)
        rt.launch(k, gsize, lsize, means2d.data, conic.data, opac.data, features.data, _buf(rt, sorted_values),
                  tile_ranges.data, np.int32(width), np.int32(height), np.int32(tiles_x),
                  raster_out.T_final.data, raster_out.last.data, v_out.data, v_alpha.data,
                  grads["v_means2d"].data, grads["v_conic"].data, grads["v_opac"].data, grads["v_features"].data,
                  _buf(rt, v_entry))
    if det:
        # the sorted entry of each binning slot, then per Gaussian the sum of its entries' terms in
        # binning order (the same order as summing at the slots: the same bits)
        entry_of = rt.empty((M,), np.int32)
        entry_of.fill(np.int32(-1))
        n_tiles = int(tile_ranges.shape[0])
        ke = rt.kernel("rasterize_bwd.cl", "rasterize_bwd_entry_of", opts)
        rt.launch_1d(ke, n_tiles, 64, _buf(rt, sorted_values), tile_ranges.data, np.int32(n_tiles),
                     np.int32(tiles_x), rect.data, offsets.data, entry_of.data)
        kg = rt.kernel("rasterize_bwd.cl", "rasterize_bwd_gather", opts)
        wg = 64
        rt.launch_1d(kg, N, wg, v_entry.data, entry_of.data, offsets.data, np.int32(N), np.int32(M),
                     grads["v_means2d"].data, grads["v_conic"].data, grads["v_opac"].data, grads["v_features"].data)
    return grads


def rasterize_projected(rt, proj, binned, width: int, height: int, choice: RasterChoice = None) -> RasterOut:
    """``rasterize`` of the stage records: proj (ops.project.Projected), binned (ops.binning.Binned)."""
    return rasterize(rt, proj.means2d, proj.conic, proj.opac, proj.features, binned.sorted_values,
                     binned.tile_ranges, width, height, choice)


def rasterize_projected_bwd(rt, proj, binned, raster: RasterOut, v_out, v_alpha, width: int, height: int,
                            deterministic: bool = False, choice: RasterChoice = None) -> Dict[str, "object"]:
    """``rasterize_bwd`` of the stage records (as rasterize_projected); deterministic: a bool, the
    rects and binning offsets it needs are taken from proj and binned."""
    return rasterize_bwd(rt, proj.means2d, proj.conic, proj.opac, proj.features, binned.sorted_values,
                         binned.tile_ranges, width, height, raster, v_out, v_alpha,
                         deterministic=(proj.rect, binned.offsets) if deterministic else None, choice=choice)


def accumulate_densify_stats(rt, v_means2d, radius, width: int, height: int, grad_accum, count,
                             max_radius, rows=None, skip=None) -> None:
    """In place on the device, for Gaussians with radius > 0: grad_accum [N] += |v_means2d * (W/2, H/2)|,
    count [N] (int32) += 1, max_radius [N] = max(max_radius, radius).
    rows: None, or int32 [L] (ops.select.LiveRows.rows): v_means2d [L, 2] and radius [L] are then
    a step's on selected rows, entry i belonging to Gaussian rows[i].
    skip: None, or the step gate int32 [1] (ops.util.step_gate): nothing changes where it is not 0."""
    L = int(radius.shape[0])
    N = int(grad_accum.shape[0])
    assert v_means2d.shape == (L, 2) and count.shape == (N,) and max_radius.shape == (N,)
    assert (L == N) if rows is None else (tuple(rows.shape) == (L,) and rows.dtype == np.int32)
    assert radius.dtype == np.int32 and count.dtype == np.int32
    if L == 0:
        return
    rt.launch_1d(rt.kernel("densify_stats.cl", "accumulate_densify_stats"), L, 64, v_means2d.data, radius.data,
                 np.float32(0.5 * width), np.float32(0.5 * height), np.int32(L), rt.buf(rows),
                 np.int32(rows is not None), grad_accum.data, count.data, max_radius.data, rt.buf(skip),
                 np.int32(skip is not None))
