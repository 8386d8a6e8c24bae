"""Tile binning, tile ranges, and the bin -> sort -> ranges chain (cl/bin.cl).

See docs/ARCHITECTURE.md "bin, sort, ranges".  The rasterizer consumes the output of
:func:`bin_and_sort`, a :class:`Binned` record: sorted_values [C] int32 (Gaussian ids, per tile
front to back, in the first M of the C slots) and tile_ranges [n_tiles, 2] int32 (start, end) into
it.  The deterministic rasterize adjoint also takes the binning offsets [N + 1] (Gaussian i's entries
were emitted at offsets[i] .. offsets[i+1], its rect's tiles row-major), to file per-entry terms by
Gaussian without a search.

bin_and_sort reads nothing back on the way: the depth bounds stay on the device (depth_keys reads
them, the depth sort's passes above their bits copy), and the pair buffers hold C pairs, C sized
from the pair counts of earlier binnings on the same tile grid (PairCapacity: HEADROOM times the
latest, grown at once); the sort and the ranges take the true count M from the device.  M is copied
to the host without blocking (Binned.pairs, a PairCount) and checked where the caller next waits on
the device: an overflow (M > C: the pairs past C were not written, the list has no tile ranges) is
never used, bin_and_sort(check=True) re-emits at once and the training step re-runs (Trainer._step).
Only the first binning on a grid reads M before sizing its buffers.
"""
from __future__ import annotations

import math
from typing import NamedTuple, Optional

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from endowave_cl.layout import tile_grid  # noqa: F401  (part of this module's API)
from endowave_cl.ops.scan import exclusive_scan_with_total
from endowave_cl.ops.sort import SortConfig, config_for_bits, radix_sort_pairs

DEPTH_BITS = 32       # low key bits: the float32 depth's bit pattern
LOCAL = 64            # work-group size of the one-item-per-element kernels here
HEADROOM = 1.25       # the pair buffers hold this many times the latest pair count (PairCapacity)
MIN_CAPACITY = 1024   # and at least this many pairs
NO_BOUNDS = np.array([0xFFFFFFFF, 0], np.uint32)   # dbounds before bin_counts: (least, greatest) of none


class BinEntries(NamedTuple):
    """What :func:`bin_gaussians` emits (unsorted); unpacks as (keys, values, n_isect, offsets)."""
    keys: cla.Array        # [M] uint64: tile id << 32 | the float32 depth's bits
    values: cla.Array      # [M] int32 Gaussian ids
    n_isect: int           # M, the number of (tile, Gaussian) pairs
    offsets: cla.Array     # [N + 1] int32: Gaussian i's entries are offsets[i] .. offsets[i + 1]


class PairCapacity:
    """The pair buffers' length C that bin_and_sort gives one tile grid: HEADROOM times the latest
    pair count read back (at least MIN_CAPACITY), grown as soon as a count needs more, shrunk only
    where it needs less than half (counts that vary from frame to frame keep one size).  None
    until the first count."""

    def __init__(self):
        self.capacity: Optional[int] = None

    def observe(self, m: int) -> None:
        need = max(MIN_CAPACITY, math.ceil(int(m) * HEADROOM))
        if self.capacity is None or need > self.capacity or 2 * need < self.capacity:
            self.capacity = need


def pair_capacity(rt, tiles_x: int, tiles_y: int) -> PairCapacity:
    """The runtime's PairCapacity of a tiles_x x tiles_y grid."""
    return rt.cached(("binning.pair_capacity", int(tiles_x), int(tiles_y)), PairCapacity)


class PairCount:
    """M, the number of (tile, Gaussian) pairs of a binning, and C, the capacity its pair buffers
    were made with.  M lies on the device (offsets[N]); a copy to the host is enqueued without
    blocking when the binning is, so that reading it after any later wait on the device costs
    nothing.  value() waits for that copy (a sync only where nothing has waited since) and tells
    the grid's PairCapacity."""

    def __init__(self, capacity: int, m: Optional[int] = None, host: Optional[np.ndarray] = None, event=None,
                 policy: Optional[PairCapacity] = None):
        self.capacity = int(capacity)   # C: the pair buffers' length
        self._m = None if m is None else int(m)
        self._host = host               # [1] int32, filled by event
        self._event = event
        self._policy = policy
        self._device = None             # (buffer, int32 index) of M on the device, where it lies there
        if self._m is not None and policy is not None:
            policy.observe(self._m)

    @classmethod
    def enqueue_read(cls, rt, offsets: cla.Array, n: int, capacity: int, policy: Optional[PairCapacity]):
        """The PairCount of offsets [n + 1] (M = offsets[n]), its copy to the host enqueued."""
        host = np.empty(1, np.int32)
        event = cl.enqueue_copy(rt.queue, host, offsets.base_data, src_offset=int(offsets.offset) + 4 * int(n),
                                is_blocking=False)
        count = cls(capacity, host=host, event=event, policy=policy)
        count._device = (offsets.base_data, int(offsets.offset) // 4 + int(n))
        return count

    def device_at(self):
        """(buffer, int32 index) where M lies on the device (ops.util.step_gate tests it there), or
        None where it was known on the host when the buffers were sized."""
        return self._device

    @property
    def pending(self) -> bool:
        """True while the copy of M has not completed (value() would wait on the device)."""
        return self._m is None and self._event.command_execution_status != cl.command_execution_status.COMPLETE

    def value(self) -> int:
        """M (waits for its copy where it is pending)."""
        if self._m is None:
            self._event.wait()
            self._m = int(self._host[0])
            self._event = self._host = None
            if self._policy is not None:
                self._policy.observe(self._m)
        return self._m

    @property
    def overflowed(self) -> bool:
        """M > C: the pairs past C were not written and the list has no tile ranges."""
        return self.value() > self.capacity


class Binned(NamedTuple):
    """The binning stage's record (:func:`bin_and_sort`); unpacks as (sorted_values, tile_ranges,
    pairs, offsets)."""
    sorted_values: cla.Array   # [C] int32 Gaussian ids, tile-major then front to back, in the first M
    tile_ranges: cla.Array     # [n_tiles, 2] int32 (start, end) of each tile's run; (0, 0) if empty
    pairs: PairCount           # M (read without blocking) and C
    offsets: cla.Array         # [N + 1] int32 binning offsets (see BinEntries); offsets[N] = M

    @property
    def n_isect(self) -> int:
        """M, the number of (tile, Gaussian) pairs (waits for its copy where it is pending)."""
        return self.pairs.value()

    @property
    def overflowed(self) -> bool:
        """The pairs did not fit the buffers (M > C): the record must not be used."""
        return self.pairs.overflowed


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
    cl.enqueue_fill_buffer(rt.queue, dbounds.base_data, NO_BOUNDS, int(dbounds.offset), NO_BOUNDS.nbytes)
    _launch(rt, "bin_counts", n, radius.data, tiles_touched.data, depth.data, np.int32(n), counts.data,
            dbounds.data)
    return counts, dbounds


def _counted(rt, radius, tiles_touched, depth):
    """(counts [N], dbounds [2], offsets [N + 1], M): _counts, the binning offsets in id order (the
    exclusive scan of counts, then the total) and M read back (bin_gaussians sizes its output by it)."""
    n = int(depth.size)
    counts, dbounds = _counts(rt, radius, tiles_touched, depth)
    offsets = exclusive_scan_with_total(rt, counts)  # [N + 1]
    return counts, dbounds, offsets, int(offsets[n:n + 1].get()[0])


def depth_order(rt, depth: cla.Array, counts: cla.Array, dbounds: cla.Array,
                sort_config: Optional[SortConfig] = None):
    """(order [N] int32, key_bits [1] int32 device array): the Gaussian ids sorted by depth (the
    float32 bit pattern as a uint, as the keys of bin_gaussians), equal depths in id order; the
    Gaussians without entries (counts 0) anywhere.  Nothing is read back: the keys are the patterns
    less the least of those with entries (dbounds [2], bin_counts' device array, read by depth_keys),
    which also writes the bits they span to key_bits; the sort runs DEPTH_BITS bits' passes and
    those above key_bits copy (ops.sort.radix_sort_pairs limits)."""
    n = int(depth.size)
    keys = rt.empty(n, np.uint64)      # [N]
    ids = rt.empty(n, np.int32)        # [N]
    key_bits = rt.empty(1, np.int32)   # [1]
    _launch(rt, "depth_keys", n, depth.data, counts.data, np.int32(n), dbounds.data, keys.data, ids.data,
            key_bits.data)
    _, order = radix_sort_pairs(rt, keys, ids, DEPTH_BITS, sort_config, limits=key_bits, bits_at=0)
    return order, key_bits


def tile_ranges(rt, sorted_keys: cla.Array, n_tiles: int, shift: int = DEPTH_BITS,
                count: Optional[cla.Array] = None, count_at: int = -1) -> cla.Array:
    """[n_tiles, 2] int32 (start, end) of each tile's run in sorted_keys [M] (tile = key >> shift);
    (0, 0) if empty.  count (int32 device array) with count_at >= 0: the keys are the first
    count[count_at] of sorted_keys' M, and none where it is more than M (an overflowed list)."""
    q = rt.queue
    ranges = cla.zeros(q, (int(n_tiles), 2), np.int32, allocator=rt.pool())
    m = int(sorted_keys.size)
    if m > 0 and n_tiles > 0:
        _launch(rt, "tile_ranges", m, sorted_keys.data, np.int32(m), np.int32(n_tiles), np.int32(shift),
                ranges.data, rt.buf(count), np.int32(count_at if count is not None else -1))
    return ranges


def bin_and_sort(rt, rect: cla.Array, depth: cla.Array, radius: cla.Array, tiles_touched: cla.Array,
                 width: int, height: int, sort_config: Optional[SortConfig] = None,
                 capacity: Optional[int] = None, check: bool = True) -> Binned:
    """Binned(sorted_values [C] int32, tile_ranges [n_tiles, 2] int32, pairs (M and C), offsets
    [N + 1] int32) for a width x height image.

    The order is that of sorting bin_gaussians' (tile << 32 | depth bits) keys stably, reached in
    two stages with fewer radix passes over the M entries: the N Gaussians are sorted by depth
    (depth_order: only the depth bits the visible Gaussians span), their entries are emitted in that
    order with the tile id alone as the key (cl/bin.cl bin_in_order), and a stable sort of the tile
    bits (one pass on CPU devices up to 2^11 tiles: ops.sort.config_for_bits) leaves each tile's
    entries in depth order, equal depths in id order.  sort_config, when given, runs both sorts.
    offsets are the binning offsets in id order (bin_gaussians'), which the deterministic adjoint
    files its per-entry terms by; the emission order does not enter them.

    The pairs fill the first M of C slots.  capacity: C (default: the grid's PairCapacity; the
    first binning on a grid reads M back and sizes C from it).  check: wait for M and, where it
    overflowed C, emit again into buffers sized from it (a sync on the device); check=False leaves
    that to the caller (Binned.overflowed after its own wait: the training step's read-back)."""
    tiles_x, tiles_y = tile_grid(width, height)
    n_tiles = tiles_x * tiles_y
    n = int(depth.size)
    if n == 0:
        keys, values, _, offsets = _no_entries(rt)
        return Binned(values, tile_ranges(rt, keys, n_tiles, 0), PairCount(0, 0), offsets)
    counts, dbounds = _counts(rt, radius, tiles_touched, depth)
    offsets = exclusive_scan_with_total(rt, counts)                      # [N + 1], offsets[N] = M
    policy = pair_capacity(rt, tiles_x, tiles_y) if capacity is None else None
    m = None
    if policy is not None and policy.capacity is None:   # the grid's first binning: M read before sizing C
        m = int(offsets[n:n + 1].get()[0])
        policy.observe(m)
    cap = policy.capacity if policy is not None else max(1, int(capacity))
    pairs = PairCount(cap, m) if m is not None else PairCount.enqueue_read(rt, offsets, n, cap, policy)
    order, _ = depth_order(rt, depth, counts, dbounds, sort_config)      # [N]
    counts_r = rt.empty(n, np.int32)                                     # [N] in depth order
    _launch(rt, "counts_in_order", n, order.data, counts.data, np.int32(n), counts_r.data)
    offsets_r = exclusive_scan_with_total(rt, counts_r)                  # [N + 1]
    binned = _emit_sorted(rt, rect, order, offsets_r, offsets, pairs, tiles_x, n_tiles, sort_config)
    if check and binned.overflowed:      # M > C: the same entries again, into buffers sized from M
        fit = PairCapacity()
        fit.observe(pairs.value())
        binned = _emit_sorted(rt, rect, order, offsets_r, offsets, PairCount(fit.capacity, pairs.value()),
                              tiles_x, n_tiles, sort_config)
    return binned


def _emit_sorted(rt, rect, order, offsets_r, offsets, pairs: PairCount, tiles_x: int, n_tiles: int,
                 sort_config: Optional[SortConfig]) -> Binned:
    """bin_and_sort's second stage into buffers of pairs.capacity: the entries emitted in depth order
    (offsets_r [N + 1]) with the tile as the key, sorted by tile, their ranges; the sort and the
    ranges take M from offsets [N + 1] on the device."""
    n = int(order.size)
    cap = pairs.capacity
    keys = rt.empty(cap, np.uint64)    # [C]
    values = rt.empty(cap, np.int32)   # [C]
    _launch(rt, "bin_in_order", n, rect.data, order.data, offsets_r.data, np.int32(n), np.int32(tiles_x),
            np.int32(cap), keys.data, values.data)
    tile_bits = key_bits(n_tiles) - DEPTH_BITS
    sorted_keys, sorted_values = radix_sort_pairs(rt, keys, values, tile_bits,
                                                  sort_config or config_for_bits(rt, cap, tile_bits),
                                                  limits=offsets, n_at=n)
    return Binned(sorted_values, tile_ranges(rt, sorted_keys, n_tiles, 0, offsets, n), pairs, offsets)


def bin_projected(rt, proj, width: int, height: int, sort_config: Optional[SortConfig] = None,
                  capacity: Optional[int] = None, check: bool = True) -> Binned:
    """:func:`bin_and_sort` of the projection record proj (ops.project.Projected)."""
    return bin_and_sort(rt, proj.rect, proj.depth, proj.radius, proj.tiles_touched, width, height, sort_config,
                        capacity, check)
