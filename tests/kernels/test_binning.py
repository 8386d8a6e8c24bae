"""Tile binning (cl/bin.cl), tile ranges and the bin -> sort -> ranges chain, exactly against
the numpy reference (endowave_cl/reference/binning.py).  Integer ops: no adjoint."""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pytest

from conftest import small
from endowave_cl.ops import binning as B
from endowave_cl.ops.sort import SortConfig
from endowave_cl.reference.binning import (bin_gaussians_ref, bin_offsets_ref, sort_pairs_ref, tile_grid,
                                           tile_ranges_ref)


def _scene(rng, n, tiles_x, tiles_y, max_side=4, p_culled=0.2):
    """Random projected Gaussians: rects clamped to the grid, tiles_touched = rect area,
    some culled (radius 0, empty rect, no tiles), depths with duplicates."""
    x0 = rng.integers(-2, tiles_x, n)
    y0 = rng.integers(-2, tiles_y, n)
    x1 = x0 + rng.integers(1, max_side + 1, n)
    y1 = y0 + rng.integers(1, max_side + 1, n)
    rect = np.stack([np.clip(x0, 0, tiles_x), np.clip(y0, 0, tiles_y),
                     np.clip(x1, 0, tiles_x), np.clip(y1, 0, tiles_y)], 1).astype(np.int32)
    radius = rng.integers(1, 40, n).astype(np.int32)
    area = (rect[:, 2] - rect[:, 0]).clip(0) * (rect[:, 3] - rect[:, 1]).clip(0)
    culled = (rng.random(n) < p_culled) | (area == 0)
    radius[culled] = 0
    tiles_touched = np.where(culled, 0, area).astype(np.int32)
    depth = rng.choice(rng.uniform(0.05, 10.0, max(1, n // 3)), n).astype(np.float32)
    return rect, depth, radius, tiles_touched


def _dev(rt, *arrays):
    return [cla.to_device(rt.queue, np.ascontiguousarray(a)) for a in arrays]


def _check_binning(rt, rect, depth, radius, tiles_touched, tiles_x, tiles_y):
    keys, vals, m, offsets = B.bin_gaussians(rt, *_dev(rt, rect, depth, radius, tiles_touched), tiles_x, tiles_y)
    ref_k, ref_v = bin_gaussians_ref(rect, depth, radius, tiles_x)
    assert m == len(ref_k)
    np.testing.assert_array_equal(offsets.get(), bin_offsets_ref(rect, radius))
    assert keys.dtype == np.uint64 and vals.dtype == np.int32 and keys.shape == (m,)
    np.testing.assert_array_equal(keys.get(), ref_k)
    np.testing.assert_array_equal(vals.get(), ref_v)
    return ref_k


def _check_chain(rt, rect, depth, radius, tiles_touched, width, height, config=None, capacity=None):
    """bin_and_sort (checked: an overflow of capacity is emitted again) against the reference: the
    first M of the C >= M slots, the ranges and offsets exactly."""
    tiles_x, tiles_y = tile_grid(width, height)
    n_tiles = tiles_x * tiles_y
    b = B.bin_and_sort(rt, *_dev(rt, rect, depth, radius, tiles_touched), width, height, sort_config=config,
                       capacity=capacity)
    sv, ranges, m, offsets = b.sorted_values, b.tile_ranges, b.n_isect, b.offsets
    np.testing.assert_array_equal(offsets.get(), bin_offsets_ref(rect, radius))
    ref_k, ref_v = sort_pairs_ref(*bin_gaussians_ref(rect, depth, radius, tiles_x))
    assert not b.overflowed and b.pairs.capacity == sv.shape[0]
    assert m == len(ref_k) and sv.shape[0] >= m and sv.dtype == np.int32
    assert ranges.shape == (n_tiles, 2) and ranges.dtype == np.int32
    np.testing.assert_array_equal(sv.get()[:m], ref_v)
    np.testing.assert_array_equal(ranges.get(), tile_ranges_ref(ref_k, n_tiles))
    return b


# --- binning ------------------------------------------------------------------------------------

@pytest.mark.parametrize("tiles_x,tiles_y", [(1, 1), (7, 5), (40, 32), (13, 29)])
@pytest.mark.parametrize("n", [1, 63, 64, 65, 1000])
def test_bin_gaussians_matches_reference(rt, n, tiles_x, tiles_y):
    rng = np.random.default_rng(n * 100 + tiles_x)
    _check_binning(rt, *_scene(rng, n, tiles_x, tiles_y), tiles_x, tiles_y)


def test_bin_empty_input(rt):
    z = np.zeros(0, np.int32)
    keys, vals, m, offsets = B.bin_gaussians(rt, *_dev(rt, np.zeros((0, 4), np.int32), np.zeros(0, np.float32), z, z),
                                             4, 3)
    assert m == 0 and keys.shape == (0,) and vals.shape == (0,)
    np.testing.assert_array_equal(offsets.get(), [0])


def test_bin_all_culled(rt):
    rng = np.random.default_rng(2)
    rect, depth, radius, tt = _scene(rng, 50, 9, 6)
    radius[:] = 0
    tt[:] = 0
    keys, vals, m, offsets = B.bin_gaussians(rt, *_dev(rt, rect, depth, radius, tt), 9, 6)
    assert m == 0 and keys.size == 0
    np.testing.assert_array_equal(offsets.get(), np.zeros(51, np.int32))


def test_bin_radius_zero_ignores_stale_tiles_touched(rt):
    """A culled Gaussian (radius 0) adds nothing, whatever its rect and tiles_touched say."""
    rng = np.random.default_rng(4)
    rect, depth, radius, tt = _scene(rng, 200, 11, 7, p_culled=0.0)
    radius[::3] = 0  # tiles_touched and rect still non-empty for these
    _check_binning(rt, rect, depth, radius, tt, 11, 7)


def test_bin_one_gaussian_covers_all_tiles(rt):
    tiles_x, tiles_y = 23, 9
    rect = np.array([[0, 0, tiles_x, tiles_y], [3, 2, 5, 4]], np.int32)
    depth = np.array([2.5, 1.0], np.float32)
    radius = np.array([5000, 10], np.int32)
    tt = np.array([tiles_x * tiles_y, 4], np.int32)
    keys = _check_binning(rt, rect, depth, radius, tt, tiles_x, tiles_y)
    assert len(keys) == tiles_x * tiles_y + 4


# --- ranges -------------------------------------------------------------------------------------

def test_tile_ranges_matches_reference(rt):
    rng = np.random.default_rng(8)
    n_tiles = 37
    tiles = np.sort(rng.choice([0, 3, 4, 5, 17, 36], 500)).astype(np.uint64)
    keys = (tiles << np.uint64(32)) | rng.integers(0, 2 ** 32, 500, dtype=np.uint64)
    r = B.tile_ranges(rt, cla.to_device(rt.queue, keys), n_tiles)
    np.testing.assert_array_equal(r.get(), tile_ranges_ref(keys, n_tiles))


def test_tile_ranges_single_entry_and_empty(rt):
    keys = np.array([np.uint64(6) << np.uint64(32)], np.uint64)
    r = B.tile_ranges(rt, cla.to_device(rt.queue, keys), 10).get()
    np.testing.assert_array_equal(r, tile_ranges_ref(keys, 10))
    assert tuple(r[6]) == (0, 1)
    r0 = B.tile_ranges(rt, cla.empty(rt.queue, 0, np.uint64), 10).get()
    np.testing.assert_array_equal(r0, np.zeros((10, 2), np.int32))


# --- the chain ----------------------------------------------------------------------------------

@pytest.mark.parametrize("width,height", [(16, 16), (100, 37), (640, 512), (333, 211)])
def test_bin_and_sort_matches_reference(rt, width, height):
    tiles_x, tiles_y = tile_grid(width, height)
    rng = np.random.default_rng(width)
    _check_chain(rt, *_scene(rng, 3000, tiles_x, tiles_y, max_side=5), width, height)


@pytest.mark.parametrize("cfg", [SortConfig(radix_bits=4, wg=8, items_min=3, items_max=3),
                                 SortConfig(radix_bits=8, wg=4, items_min=7, items_max=7)])
def test_bin_and_sort_other_sort_configs(rt, cfg):
    rng = np.random.default_rng(12)
    _check_chain(rt, *_scene(rng, 700, 12, 10), 190, 150, config=cfg)


def test_bin_and_sort_empty(rt):
    z = np.zeros(0, np.int32)
    b = B.bin_and_sort(rt, *_dev(rt, np.zeros((0, 4), np.int32), np.zeros(0, np.float32), z, z), 50, 40)
    assert b.n_isect == 0 and b.sorted_values.shape == (0,) and not b.overflowed
    np.testing.assert_array_equal(b.tile_ranges.get(), np.zeros((4 * 3, 2), np.int32))


def test_bin_and_sort_100k_gaussians(rt):
    """The benchmark's scene size: 100k Gaussians of 1-3 tiles per side on a 40 x 32 grid."""
    rng = np.random.default_rng(100)
    _check_chain(rt, *_scene(rng, 100_000, 40, 32, max_side=3, p_culled=0.1), 640, 512)


def test_key_bits():
    assert B.key_bits(1) == 32 and B.key_bits(2) == 33 and B.key_bits(1280) == 43
    assert B.key_bits(1024) == 42 and B.key_bits(1025) == 43
    assert B.tile_grid(640, 512) == (40, 32) and B.tile_grid(641, 1) == (41, 1)


@pytest.mark.oclgrind
def test_bin_and_sort_tiny(rt):
    rng = np.random.default_rng(20)
    n = small(20, 20)
    rect, depth, radius, tt = _scene(rng, n, 5, 3, max_side=3)
    rect[0] = (0, 0, 5, 3)  # one Gaussian covers every tile
    radius[0], tt[0] = 99, 15
    _check_binning(rt, rect, depth, radius, tt, 5, 3)
    _check_chain(rt, rect, depth, radius, tt, 80, 40)


# --- the two-stage order (bin_and_sort: depth first, then the tile) -----------------------------

@pytest.mark.parametrize("depths", ["equal", "narrow", "negative", "culled_extremes"])
def test_bin_and_sort_depth_first_keeps_the_order(rt, depths):
    """bin_and_sort's two stages (the Gaussians sorted by depth, their entries emitted in that order
    and sorted by tile) give exactly the order of the full keys: all depths equal (no depth bits), a
    narrow range, sign-bit patterns (negative depths sort after positive ones as uint bits), and
    culled Gaussians with extreme depths that must not widen the depth bits."""
    rng = np.random.default_rng(31)
    rect, depth, radius, tt = _scene(rng, 2000, 13, 9, max_side=3)
    if depths == "equal":
        depth[:] = 4.0
    elif depths == "narrow":
        depth = (4.0 + rng.integers(0, 5, depth.size) * np.float32(2 ** -20)).astype(np.float32)
    elif depths == "negative":
        depth = np.where(rng.random(depth.size) < 0.3, -depth, depth).astype(np.float32)
    else:
        depth[radius == 0] = np.where(rng.random(int((radius == 0).sum())) < 0.5, 1e-30, 1e30)
    _check_chain(rt, rect, depth, radius, tt, 13 * 16 - 5, 9 * 16)
    d_rect, d_depth, d_radius, d_tt = _dev(rt, rect, depth, radius, tt)
    counts, dbounds = B._counts(rt, d_radius, d_tt, d_depth)
    order, key_bits = B.depth_order(rt, d_depth, counts, dbounds)
    vis = radius > 0
    bits = depth.view(np.uint32).astype(np.int64)
    assert int(key_bits.get()[0]) == int(bits[vis].max() - bits[vis].min()).bit_length()
    # the Gaussians with entries in (depth bits, id) order; the others may lie anywhere
    o = order.get()
    assert sorted(o.tolist()) == list(range(depth.size))
    o_vis = o[vis[o]]
    np.testing.assert_array_equal(o_vis, np.flatnonzero(vis)[np.argsort(bits[vis], kind="stable")])


# --- what bin_and_sort keeps on the device: the depth bounds and the pair count ------------------

def test_depth_bounds_stay_on_the_device(rt):
    """bin_counts' (least, greatest) depth pattern of the Gaussians with entries, and depth_keys'
    keys (pattern - least) and key bits read from them on the device; with no entries: (UINT_MAX, 0),
    zero keys, zero bits."""
    rng = np.random.default_rng(41)
    rect, depth, radius, tt = _scene(rng, 500, 9, 7)
    depth[radius == 0] = 1e30                   # the culled Gaussians do not widen the bounds
    vis = radius > 0
    bits = depth.view(np.uint32).astype(np.int64)
    for case in ("some", "none"):
        if case == "none":
            radius[:] = 0
            vis[:] = False
        d_rect, d_depth, d_radius, d_tt = _dev(rt, rect, depth, radius, tt)
        counts, dbounds = B._counts(rt, d_radius, d_tt, d_depth)
        lo, hi = (int(bits[vis].min()), int(bits[vis].max())) if vis.any() else (0xFFFFFFFF, 0)
        np.testing.assert_array_equal(dbounds.get(), np.array([lo, hi], np.uint32))
        n = depth.size
        keys, ids, key_bits = rt.empty(n, np.uint64), rt.empty(n, np.int32), rt.empty(1, np.int32)
        rt.launch_1d(rt.kernel("bin.cl", "depth_keys"), n, B.LOCAL, d_depth.data, counts.data, np.int32(n),
                     dbounds.data, keys.data, ids.data, key_bits.data)
        want = np.where(vis, bits - (lo if vis.any() else 0), 0).astype(np.uint64)
        np.testing.assert_array_equal(keys.get(), want)
        np.testing.assert_array_equal(ids.get(), np.arange(n))
        assert int(key_bits.get()[0]) == (int(hi - lo).bit_length() if vis.any() else 0)


def test_pair_capacity_headroom_growth_and_shrink():
    p = B.PairCapacity()
    assert p.capacity is None
    p.observe(0)
    assert p.capacity == B.MIN_CAPACITY
    p.observe(100_000)
    assert p.capacity == int(np.ceil(100_000 * B.HEADROOM))
    p.observe(70_000)                            # less, but not under half: kept
    assert p.capacity == int(np.ceil(100_000 * B.HEADROOM))
    p.observe(40_000)                            # needs under half: shrunk
    assert p.capacity == int(np.ceil(40_000 * B.HEADROOM))


@pytest.mark.parametrize("capacity", [1, 37, 400])
def test_bin_and_sort_overflow_is_emitted_again(rt, capacity):
    """A capacity below the pair count: the checked binning (the default) re-emits into buffers
    sized from the count, with exactly the reference's result."""
    rng = np.random.default_rng(capacity)
    rect, depth, radius, tt = _scene(rng, 600, 11, 9, max_side=4)
    b = _check_chain(rt, rect, depth, radius, tt, 11 * 16, 9 * 16, capacity=capacity)
    assert b.n_isect > capacity and b.pairs.capacity >= b.n_isect


def test_bin_and_sort_unchecked_overflow_is_flagged_and_empty(rt):
    """check=False with a capacity below the pair count: nothing past the capacity is written, the
    record says it overflowed (with the true count), and it has no tile ranges, so that a rasterizer
    run on it reads only what exists; re-binning with room gives the reference."""
    rng = np.random.default_rng(43)
    rect, depth, radius, tt = _scene(rng, 400, 10, 6)
    m = len(bin_gaussians_ref(rect, depth, radius, 10)[0])
    b = B.bin_and_sort(rt, *_dev(rt, rect, depth, radius, tt), 160, 96, capacity=m - 1, check=False)
    assert b.sorted_values.shape == (m - 1,) and b.overflowed and b.n_isect == m
    np.testing.assert_array_equal(b.tile_ranges.get(), 0)
    _check_chain(rt, rect, depth, radius, tt, 160, 96, capacity=m)          # exactly enough: no overflow


def test_bin_and_sort_reads_the_count_only_on_a_grids_first_binning(rt, monkeypatch):
    """The first binning on a tile grid reads M back to size its buffers; later ones read nothing
    (the count is copied without blocking), and reading it after a wait does not wait."""
    import pyopencl as cl
    reads = []
    plain = cl.enqueue_copy

    def counted(queue, dest, src, **kw):
        if isinstance(dest, np.ndarray) and kw.get("is_blocking", True):
            reads.append(dest.nbytes)
        return plain(queue, dest, src, **kw)
    monkeypatch.setattr(cl, "enqueue_copy", counted)
    rng = np.random.default_rng(44)
    w, h = 16 * 23 - 3, 16 * 19 - 1             # a grid no other test bins
    rect, depth, radius, tt = _scene(rng, 800, 23, 19)
    dev = _dev(rt, rect, depth, radius, tt)
    assert B.pair_capacity(rt, 23, 19).capacity is None
    b1 = B.bin_and_sort(rt, *dev, w, h, check=False)
    assert len(reads) == 1 and not b1.overflowed
    b2 = B.bin_and_sort(rt, *dev, w, h, check=False)
    assert len(reads) == 1
    b2.tile_ranges.get()                        # a wait on the device
    assert not b2.pairs.pending and b2.n_isect == b1.n_isect and len(reads) == 2
    assert B.pair_capacity(rt, 23, 19).capacity == int(np.ceil(b1.n_isect * B.HEADROOM))


@pytest.mark.oclgrind
@pytest.mark.parametrize("variant", ["scalar", "default"])
def test_bin_and_sort_overflow_tiny(rt, variant):
    """The overflow path under Oclgrind: an unchecked overflowed list (the bin, the sort and the
    ranges past the capacity) and the rasterizer and its deterministic adjoint run on it read and
    write only inside their buffers; the checked one re-emits to the reference."""
    from endowave_cl.ops.rasterize import RasterChoice, rasterize, rasterize_bwd
    rng = np.random.default_rng(45)
    rect, depth, radius, tt = _scene(rng, small(40, 24), 5, 3, max_side=3)
    _check_chain(rt, rect, depth, radius, tt, 80, 40, capacity=3)
    d_rect, d_depth, d_radius, d_tt = _dev(rt, rect, depth, radius, tt)
    b = B.bin_and_sort(rt, d_rect, d_depth, d_radius, d_tt, 80, 40, capacity=3, check=False)
    assert b.overflowed
    n, c = depth.size, 3
    means2d = cla.to_device(rt.queue, rng.uniform(0, 40, (n, 2)).astype(np.float32))
    conic = cla.to_device(rt.queue, np.tile(np.float32([0.05, 0.0, 0.05]), (n, 1)))
    opac = cla.to_device(rt.queue, np.full(n, 0.5, np.float32))
    feats = cla.to_device(rt.queue, rng.random((n, c)).astype(np.float32))
    choice = RasterChoice("scalar") if variant == "scalar" else None   # default: the device's (vector on CPUs)
    out = rasterize(rt, means2d, conic, opac, feats, b.sorted_values, b.tile_ranges, 80, 40, choice)
    v_out = cla.to_device(rt.queue, rng.standard_normal((40, 80, c)).astype(np.float32))
    v_alpha = cla.zeros(rt.queue, (40, 80), np.float32)
    grads = rasterize_bwd(rt, means2d, conic, opac, feats, b.sorted_values, b.tile_ranges, 80, 40, out, v_out,
                          v_alpha, deterministic=(d_rect, b.offsets), choice=choice)
    assert np.all(out.alpha.get() == 0) and np.all(grads["v_opac"].get() == 0)
