"""Tile binning, tile ranges, and the bin -> sort -> ranges chain (cl/bin.cl).

See docs/ARCHITECTURE.md "bin, sort, ranges".  The rasterizer consumes the output of
:func:`bin_and_sort`, a :class:`Binned` record: sorted_values [M] int32 (Gaussian ids, per tile
front to back) and tile_ranges [n_tiles, 2] int32 (start, end) into it.  The deterministic rasterize adjoint also
takes the binning offsets [N + 1] (Gaussian i's entries were emitted at offsets[i] .. offsets[i+1],
its rect's tiles row-major), to file per-entry terms by Gaussian without a search.
"""
from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np
import pyopencl.array as cla

from endowave_cl.layout import tile_grid  # noqa: F401  (part of this module's API)
from endowave_cl.ops.scan import exclusive_scan_with_total
from endowave_cl.ops.sort import SortConfig, config_for_bits, radix_sort_pairs

DEPTH_BITS = 32  # low key bits: the float32 depth's bit pattern
LOCAL = 64       # work-group size of the one-item-per-element kernels here


class BinEntries(NamedTuple):
    """What :func:`bin_gaussians` emits (unsorted); unpacks as (keys, values, n_isect, offsets)."""
    keys: cla.Array        # [M] uint64: tile id << 32 | the float32 depth's bits
    values: cla.Array      # [M] int32 Gaussian ids
    n_isect: int           # M, the number of (tile, Gaussian) pairs
    offsets: cla.Array     # [N + 1] int32: Gaussian i's entries are offsets[i] .. offsets[i + 1]


class Binned(NamedTuple):
    """The binning stage's record (:func:`bin_and_sort`); unpacks as (sorted_values, tile_ranges,
    n_isect, offsets)."""
    sorted_values: cla.Array   # [M] int32 Gaussian ids, tile-major then front to back
    tile_ranges: cla.Array     # [n_tiles, 2] int32 (start, end) of each tile's run; (0, 0) if empty
    n_isect: int               # M
    offsets: cla.Array         # [N + 1] int32 binning offsets (see BinEntries)


def key_bits(n_tiles: int) -> int:
    """Bits of a binning key that can be set: 32 depth bits + ceil(log2(n_tiles)) tile bits."""
    return DEPTH_BITS + max(0, int(n_tiles) - 1).bit_length()


def _launch(rt, name, n, *args):
    rt.launch_1d(rt.kernel("bin.cl", name), n, LOCAL, *args)


def bin_gaussians(rt, rect: cla.Array, depth: cla.Array, radius: cla.Array,
                  tiles_touched: cla.Array, tiles_x: int, tiles_y: int) -> BinEntries:
    """BinEntries(keys [M] uint64, values [M] int32, M, offsets [N + 1] int32): for each Gaussian with
    radius > 0, one entry per tile of its rect, row-major, at offsets[i] (the exclusive scan of
    tiles_touched; offsets[N] = M).  key = tile id << 32 | the float32 depth's bits.

    rect [N, 4] int32 (x0, y0, x1, y1) exclusive, clamped to the tiles_x x tiles_y grid;
    depth [N] float32; radius [N] int32; tiles_touched [N] int32 (= the rect's area).
    """
    n = int(depth.size)
    if n == 0:
        return _no_entries(rt)
    counts, dbounds, offsets, m = _counted(rt, radius, tiles_touched, depth)
    keys = rt.empty(m, np.uint64)    # [M]
    values = rt.empty(m, np.int32)   # [M]
    if m > 0:
        _launch(rt, "bin_gaussians", n, rect.data, depth.data, radius.data, offsets.data,
                np.int32(n), np.int32(tiles_x), keys.data, values.data)
    return BinEntries(keys, values, m, offsets)


def _no_entries(rt) -> BinEntries:
    q = rt.queue
    return BinEntries(cla.empty(q, 0, np.uint64), cla.empty(q, 0, np.int32), 0, cla.zeros(q, 1, np.int32))


def _counts(rt, radius, tiles_touched, depth):
    """(counts [N] int32, dbounds [2] uint32): each Gaussian's entries (bin_counts) and the least
    and greatest depth bit pattern of those that have any ((UINT_MAX, 0) when none has)."""
    n = int(depth.size)
    counts = rt.empty(n, np.int32)  # [N]
    dbounds = rt.empty(2, np.uint32)
    dbounds.fill(np.uint32(0xFFFFFFFF))
    dbounds[1:2].fill(np.uint32(0))
    _launch(rt, "bin_counts", n, radius.data, tiles_touched.data, depth.data, np.int32(n), counts.data,
            dbounds.data)
    return counts, dbounds


def _counted(rt, radius, tiles_touched, depth):
    """(counts [N], dbounds [2], offsets [N + 1], M): _counts, the binning offsets in id order (the
    exclusive scan of counts, then the total) and M read back."""
    n = int(depth.size)
    counts, dbounds = _counts(rt, radius, tiles_touched, depth)
    offsets = exclusive_scan_with_total(rt, counts)  # [N + 1]
    return counts, dbounds, offsets, int(offsets[n:n + 1].get()[0])


def depth_order(rt, depth: cla.Array, counts: cla.Array, dbounds, sort_config: Optional[SortConfig] = None):
    """(order [N] int32, depth_bits): the Gaussian ids sorted by depth (the float32 bit pattern as a
    uint, as the keys of bin_gaussians), equal depths in id order; the Gaussians without entries
    (counts 0) anywhere.  The sort keys only the depth_bits that the patterns of the Gaussians with
    entries span (dbounds [2], bin_counts' device array, read back here)."""
    n = int(depth.size)
    lo, hi = (int(v) for v in dbounds.get())
    dmin, dbits = (lo, (hi - lo).bit_length()) if lo <= hi else (0, 0)
    keys = rt.empty(n, np.uint64)  # [N]
    ids = rt.empty(n, np.int32)    # [N]
    _launch(rt, "depth_keys", n, depth.data, counts.data, np.int32(n), np.uint32(dmin), keys.data, ids.data)
    _, order = radix_sort_pairs(rt, keys, ids, dbits, sort_config)
    return order, dbits


def tile_ranges(rt, sorted_keys: cla.Array, n_tiles: int, shift: int = DEPTH_BITS) -> cla.Array:
    """[n_tiles, 2] int32 (start, end) of each tile's run in sorted_keys [M] (tile = key >> shift);
    (0, 0) if empty."""
    q = rt.queue
    ranges = cla.zeros(q, (int(n_tiles), 2), np.int32, allocator=rt.pool())
    m = int(sorted_keys.size)
    if m > 0 and n_tiles > 0:
        _launch(rt, "tile_ranges", m, sorted_keys.data, np.int32(m), np.int32(n_tiles), np.int32(shift),
                ranges.data)
    return ranges


def bin_and_sort(rt, rect: cla.Array, depth: cla.Array, radius: cla.Array, tiles_touched: cla.Array,
                 width: int, height: int, sort_config: Optional[SortConfig] = None) -> Binned:
    """Binned(sorted_values [M] int32, tile_ranges [n_tiles, 2] int32, M, offsets [N + 1] int32) for
    a width x height image.

    The order is that of sorting bin_gaussians' (tile << 32 | depth bits) keys stably, reached in
    two stages with fewer radix passes over the M entries: the N Gaussians are sorted by depth
    (depth_order: only the depth bits the visible Gaussians span), their entries are emitted in that
    order with the tile id alone as the key (cl/bin.cl bin_in_order), and a stable sort of the tile
    bits (one pass on CPU devices up to 2^11 tiles: ops.sort.config_for_bits) leaves each tile's
    entries in depth order, equal depths in id order.  sort_config, when given, runs both sorts.
    offsets are the binning offsets in id order (bin_gaussians'), which the deterministic adjoint
    files its per-entry terms by; the emission order does not enter them."""
    tiles_x, tiles_y = tile_grid(width, height)
    n_tiles = tiles_x * tiles_y
    n = int(depth.size)
    if n == 0:
        keys, values, m, offsets = _no_entries(rt)
        return Binned(values, tile_ranges(rt, keys, n_tiles, 0), 0, offsets)
    counts, dbounds, offsets, m = _counted(rt, radius, tiles_touched, depth)
    keys = rt.empty(m, np.uint64)    # [M]
    values = rt.empty(m, np.int32)   # [M]
    if m == 0:
        return Binned(values, tile_ranges(rt, keys, n_tiles, 0), 0, offsets)
    order, _ = depth_order(rt, depth, counts, dbounds, sort_config)      # [N]
    counts_r = rt.empty(n, np.int32)                                     # [N] in depth order
    _launch(rt, "counts_in_order", n, order.data, counts.data, np.int32(n), counts_r.data)
    offsets_r = exclusive_scan_with_total(rt, counts_r)                  # [N + 1]
    _launch(rt, "bin_in_order", n, rect.data, order.data, offsets_r.data, np.int32(n), np.int32(tiles_x),
            keys.data, values.data)
    tile_bits = key_bits(n_tiles) - DEPTH_BITS
    sorted_keys, sorted_values = radix_sort_pairs(rt, keys, values, tile_bits,
                                                  sort_config or config_for_bits(rt, m, tile_bits))
    return Binned(sorted_values, tile_ranges(rt, sorted_keys, n_tiles, 0), m, offsets)


def bin_projected(rt, proj, width: int, height: int, sort_config: Optional[SortConfig] = None) -> Binned:
    """:func:`bin_and_sort` of the projection record proj (ops.project.Projected)."""
    return bin_and_sort(rt, proj.rect, proj.depth, proj.radius, proj.tiles_touched, width, height, sort_config)
