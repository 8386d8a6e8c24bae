"""Stable LSD radix sort of (uint64 key, int32 value) pairs on the device (cl/sort.cl).

Per pass: block histograms -> exclusive scan of the [digit, block] counts (ops/scan.py) ->
stable scatter into the other ping-pong buffer.  Only ``ceil(num_bits / radix_bits)`` passes
run, so keys must have no set bit at or above ``passes * radix_bits`` that should matter.
The result equals numpy's ``argsort(kind='stable')`` order exactly.

Two limits can stay on the device (``limits``, an int32 array the caller's kernels wrote, so that
the host reads nothing): the number of keys (at most the buffers' length, which the launches are
sized for) and the bits the keys can have set (the passes above them copy instead of sorting).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional, Tuple

import numpy as np
import pyopencl.array as cla

from endowave_cl.ops.scan import exclusive_scan_into

KEY_BITS = 64  # keys are uint64


@dataclass(frozen=True)
class SortConfig:
    """Tuning of the sort; see benchmarks/bench_sort.py.

    radix_bits: digit width (passes = ceil(num_bits / radix_bits)).
    wg: work-items per group (local memory = 2^radix_bits * wg ints).
    items_min / items_max: bounds on the consecutive keys each work-item walks.
    groups_per_cu: how many work-groups per compute unit to aim for when picking items.
    """
    radix_bits: int = 8
    wg: int = 16
    items_min: int = 16
    items_max: int = 1 << 14
    groups_per_cu: int = 8

    def options(self):
        return [f"-DRADIX_BITS={self.radix_bits}", f"-DSORT_WG={self.wg}"]

    def items_for(self, n: int, compute_units: int) -> int:
        target = max(1, self.groups_per_cu * compute_units)
        items = -(-n // (target * self.wg))
        return int(min(self.items_max, max(self.items_min, items)))


# CPU (PoCL): few wide passes (8-bit digits: 6 passes for 44 bits; 11-bit digits, 4 passes, were
# no faster), one work-item per block (its scatter reuses the histogram's counts; measured
# fastest, wg 4 and 16 no better), long serial chunks, a handful of blocks per core.
CPU_CONFIG = SortConfig(radix_bits=8, wg=1, items_min=16, items_max=1 << 14, groups_per_cu=4)
# GPU: narrow digits so that the [digit, work-item] table fits local memory with many
# work-items; short chunks so that there are thousands of work-groups.  Its 11 passes for 44
# bits are the fastest from a few million keys on (research/PERFORMANCE.md "GPU": an H200 sorts 4M
# keys in 2.4 ms).  Below GPU_SMALL_MAX keys a sort's wall time is mostly its launches, and
# GPU_SMALL_CONFIG's 6-bit digits (8 passes, longer chunks) sort 340k-1M keys in 1.4-1.6 ms
# against 1.9-3.2 ms.
GPU_CONFIG = SortConfig(radix_bits=4, wg=128, items_min=8, items_max=32, groups_per_cu=64)
GPU_SMALL_CONFIG = SortConfig(radix_bits=6, wg=64, items_min=8, items_max=512, groups_per_cu=16)
GPU_SMALL_MAX = 1 << 21
# CPU: keys of 9 to CPU_ONE_PASS_BITS bits (bin_and_sort's tile ids: 9 bits at 320x256, 11 at
# 640x512) sort in one pass of that many bits, which costs less than two passes of 8 bits
# (research/PERFORMANCE.md, "Seventeenth pass").  Local memory: 2^11 ints with wg = 1.
CPU_ONE_PASS_BITS = 11


def _fit_local_memory(cfg: SortConfig, caps) -> SortConfig:
    """cfg with its work-group cut to what the device allows and its [digit, work-item] table to
    half the local memory."""
    wg = cfg.wg
    while wg > 1 and (wg > caps.max_work_group_size or 4 * (1 << cfg.radix_bits) * wg > caps.local_mem_size // 2):
        wg //= 2
    return cfg if wg == cfg.wg else replace(cfg, wg=wg)


def default_config(rt, n: Optional[int] = None) -> SortConfig:
    """CPU_CONFIG on devices without a reported SIMT width (DeviceCaps); else GPU_CONFIG, or
    GPU_SMALL_CONFIG for fewer than GPU_SMALL_MAX keys (n None: the large one), fitted to the
    device's work-group and local memory limits."""
    caps = getattr(rt, "caps", None)
    if caps is None or not caps.simt:
        return CPU_CONFIG
    small = n is not None and n < GPU_SMALL_MAX
    return _fit_local_memory(GPU_SMALL_CONFIG if small else GPU_CONFIG, caps)


def config_for_bits(rt, n: int, num_bits: int) -> SortConfig:
    """default_config(rt, n), except that on CPU devices keys of up to CPU_ONE_PASS_BITS bits take
    one pass of num_bits-bit digits instead of two of CPU_CONFIG's."""
    cfg = default_config(rt, n)
    if cfg is CPU_CONFIG and cfg.radix_bits < num_bits <= CPU_ONE_PASS_BITS:
        return replace(cfg, radix_bits=int(num_bits))
    return cfg


def sort_passes(num_bits: int, radix_bits: int) -> int:
    """Passes needed for the low ``num_bits`` bits (rounded up to whole digits)."""
    num_bits = max(0, min(KEY_BITS, int(num_bits)))
    return -(-num_bits // radix_bits)


def radix_sort_pairs(rt, keys: cla.Array, values: cla.Array, num_bits: int = KEY_BITS,
                     config: Optional[SortConfig] = None, limits: Optional[cla.Array] = None,
                     n_at: int = -1, bits_at: int = -1) -> Tuple[cla.Array, cla.Array]:
    """(keys_sorted [n] uint64, values_sorted [n] int32), stable by the low num_bits bits
    (rounded up to whole digits).  The inputs are left unchanged.

    limits: int32 device array (or None) with, where n_at >= 0, limits[n_at] the count of keys to
    sort (the first min(n, limits[n_at]); the outputs' tail is left undefined), and where
    bits_at >= 0, limits[bits_at] the bits the keys can have set (at most num_bits; the passes at
    or above it copy).  The launches and the pass count do not depend on them."""
    if keys.dtype != np.uint64 or values.dtype != np.int32:
        raise TypeError(f"radix_sort_pairs takes uint64 keys and int32 values, got {keys.dtype}, {values.dtype}")
    n = int(keys.size)
    if int(values.size) != n:
        raise ValueError(f"keys [{n}] and values [{values.size}] differ in length")
    cfg = config or default_config(rt, n)
    passes = sort_passes(num_bits, cfg.radix_bits)
    if n == 0 or passes == 0:
        return keys.copy(), values.copy()
    if n >= 2 ** 31 - cfg.wg * cfg.items_max:
        raise ValueError(f"radix_sort_pairs handles fewer than 2^31 keys, got {n}")

    items = cfg.items_for(n, rt.compute_units)
    n_blocks = -(-n // (cfg.wg * items))
    radix = 1 << cfg.radix_bits
    hist = rt.empty(radix * n_blocks, np.int32)     # [radix, n_blocks]
    offsets = rt.empty(radix * n_blocks, np.int32)  # [radix, n_blocks]
    bufs = [(rt.empty(n, np.uint64), rt.empty(n, np.int32))]
    if passes > 1:
        bufs.append((rt.empty(n, np.uint64), rt.empty(n, np.int32)))

    k_hist = rt.kernel("sort.cl", "radix_histogram", cfg.options())
    k_scatter = rt.kernel("sort.cl", "radix_scatter", cfg.options())
    gsize = (n_blocks * cfg.wg,)
    lsize = (cfg.wg,)
    given = limits is not None
    lim = (rt.buf(limits), np.int32(n_at if given else -1), np.int32(bits_at if given else -1))  # cl/sort.cl limits
    src_k, src_v = keys, values
    for p in range(passes):
        shift = np.int32(p * cfg.radix_bits)
        dst_k, dst_v = bufs[p % 2]
        rt.launch(k_hist, gsize, lsize, src_k.data, np.int32(n), np.int32(items), shift,
                  np.int32(n_blocks), hist.data, *lim)
        exclusive_scan_into(rt, hist, hist.size, offsets, offsets.size)
        rt.launch(k_scatter, gsize, lsize, src_k.data, src_v.data, np.int32(n), np.int32(items), shift,
                  np.int32(n_blocks), offsets.data, dst_k.data, dst_v.data, *lim)
        src_k, src_v = dst_k, dst_v
    return src_k, src_v
