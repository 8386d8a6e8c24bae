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
from endowave_cl.ops.sort import SortConfig, radix_sort_pairs

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
    return _bin(rt, rect, depth, radius, tiles_touched, tiles_x, compact=False)[0]


def _bin(rt, rect, depth, radius, tiles_touched, tiles_x: int, compact: bool):
    """(BinEntries, depth_bits): compact=False gives the full keys (depth_bits 32); compact=True keys
    tile id << depth_bits | (depth bits - least depth bits), depth_bits just enough for the range of
    the visible Gaussians' depth patterns: the same order as the full keys in fewer bits."""
    n = int(depth.size)
    q = rt.queue
    if n == 0:
        return BinEntries(cla.empty(q, 0, np.uint64), cla.empty(q, 0, np.int32), 0,
                          cla.zeros(q, 1, np.int32)), DEPTH_BITS
    counts = rt.empty(n, np.int32)  # [N]
    dbounds = rt.empty(2, np.uint32)
    dbounds.fill(np.uint32(0xFFFFFFFF))
    dbounds[1:2].fill(np.uint32(0))
    _launch(rt, "bin_counts", n, radius.data, tiles_touched.data, depth.data, np.int32(n), counts.data,
            dbounds.data)
    offsets = exclusive_scan_with_total(rt, counts)  # [N + 1]
    m = int(offsets[n:n + 1].get()[0])
    dmin, dshift = 0, DEPTH_BITS
    if compact and m > 0:
        lo, hi = (int(v) for v in dbounds.get())
        dmin, dshift = lo, (hi - lo).bit_length()
    keys = rt.empty(m, np.uint64)    # [M]
    values = rt.empty(m, np.int32)   # [M]
    if m > 0:
        _launch(rt, "bin_gaussians", n, rect.data, depth.data, radius.data, offsets.data,
                np.int32(n), np.int32(tiles_x), np.uint32(dmin), np.int32(dshift), keys.data, values.data)
    return BinEntries(keys, values, m, offsets), dshift


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
    a width x height image: scan -> bin -> radix sort of the needed key bits -> ranges.

    The keys are the compact ones (see _bin): the tile id above only as many depth bits as the
    visible depths' bit patterns span (22 for depths 3.5-4.5), so the sort runs
    ceil((tile bits + depth bits) / radix bits) passes instead of ceil(key_bits / radix bits),
    with the same order: sorted_values equal those of sorting the full keys."""
    tiles_x, tiles_y = tile_grid(width, height)
    n_tiles = tiles_x * tiles_y
    (keys, values, m, offsets), dshift = _bin(rt, rect, depth, radius, tiles_touched, tiles_x, compact=True)
    bits = key_bits(n_tiles) - DEPTH_BITS + dshift
    sorted_keys, sorted_values = radix_sort_pairs(rt, keys, values, bits, sort_config)
    return Binned(sorted_values, tile_ranges(rt, sorted_keys, n_tiles, dshift), m, offsets)


def bin_projected(rt, proj, width: int, height: int, sort_config: Optional[SortConfig] = None) -> Binned:
    """:func:`bin_and_sort` of the projection record proj (ops.project.Projected)."""
    return bin_and_sort(rt, proj.rect, proj.depth, proj.radius, proj.tiles_touched, width, height, sort_config)
