"""Exclusive scan (cl/scan.cl) and the radix sort (cl/sort.cl) against numpy, exactly.

Integer ops have no adjoint; every case compares the device result with the numpy reference
bit for bit.
"""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pytest

from conftest import small
from endowave_cl.ops import scan as S
from endowave_cl.ops import sort as R
from endowave_cl.reference.binning import sort_pairs_ref
from endowave_cl.reference.scan import exclusive_scan_ref
from endowave_cl.reference.sort import radix_histogram_ref, radix_scatter_ref

# Small configurations that make block boundaries fall inside small inputs, and exercise
# work-groups with more work-items than radix digits and the other way round.
TINY_CONFIGS = [
    R.SortConfig(radix_bits=4, wg=4, items_min=3, items_max=3, groups_per_cu=1),
    R.SortConfig(radix_bits=8, wg=2, items_min=5, items_max=5, groups_per_cu=1),
    R.SortConfig(radix_bits=3, wg=32, items_min=1, items_max=2, groups_per_cu=1),
    R.SortConfig(radix_bits=8, wg=1, items_min=9, items_max=9, groups_per_cu=1),
    R.SortConfig(radix_bits=11, wg=1, items_min=40, items_max=40, groups_per_cu=1),
]


def _keys(rng, n, n_tiles=300, n_depths=40):
    """uint64 binning-like keys with many duplicates: (tile << 32) | depth bits."""
    tiles = rng.integers(0, n_tiles, n).astype(np.uint64)
    depths = rng.uniform(0.1, 5.0, n_depths).astype(np.float32).view(np.uint32).astype(np.uint64)
    return (tiles << np.uint64(32)) | depths[rng.integers(0, n_depths, n)]


def _sort_and_check(rt, keys, num_bits, config=None):
    q = rt.queue
    vals = np.arange(len(keys), dtype=np.int32)  # value = original index: checks stability
    dk, dv = cla.to_device(q, keys), cla.to_device(q, vals)
    sk, sv = R.radix_sort_pairs(rt, dk, dv, num_bits, config)
    ref_k, ref_v = sort_pairs_ref(keys, vals)
    np.testing.assert_array_equal(sv.get(), ref_v)
    np.testing.assert_array_equal(sk.get(), ref_k)
    np.testing.assert_array_equal(dk.get(), keys)  # inputs untouched
    np.testing.assert_array_equal(dv.get(), vals)


# --- scan -------------------------------------------------------------------------------------

@pytest.mark.parametrize("n", [0, 1, 255, 256, 257, S.SCAN_BLOCK - 1, S.SCAN_BLOCK, S.SCAN_BLOCK + 1,
                               100003, S.SCAN_BLOCK * S.SCAN_BLOCK + 5])
def test_exclusive_scan_matches_cumsum(rt, n):
    rng = np.random.default_rng(n)
    x = rng.integers(0, 50, n).astype(np.int32)
    off, total = S.exclusive_scan(rt, cla.to_device(rt.queue, x))
    ref, ref_total = exclusive_scan_ref(x)
    assert off.shape == (n,) and off.dtype == np.int32
    np.testing.assert_array_equal(off.get(), ref)
    assert total == ref_total == int(x.sum())


def test_exclusive_scan_random_sizes_and_negatives(rt):
    rng = np.random.default_rng(7)
    for n in rng.integers(1, 20000, 5):
        x = rng.integers(-1000, 1000, n).astype(np.int32)
        off, total = S.exclusive_scan(rt, cla.to_device(rt.queue, x))
        ref, ref_total = exclusive_scan_ref(x)
        np.testing.assert_array_equal(off.get(), ref)
        assert total == ref_total


def test_exclusive_scan_rejects_other_dtypes(rt):
    with pytest.raises(TypeError):
        S.exclusive_scan(rt, cla.to_device(rt.queue, np.arange(4, dtype=np.float32)))


@pytest.mark.oclgrind
def test_exclusive_scan_tiny(rt):
    rng = np.random.default_rng(3)
    n = small(3 * S.SCAN_BLOCK + 7, S.SCAN_BLOCK + 3)  # two levels of block sums
    x = rng.integers(0, 9, n).astype(np.int32)
    off, total = S.exclusive_scan(rt, cla.to_device(rt.queue, x))
    ref, ref_total = exclusive_scan_ref(x)
    np.testing.assert_array_equal(off.get(), ref)
    assert total == ref_total


# --- the sort's pieces --------------------------------------------------------------------------

@pytest.mark.parametrize("cfg", TINY_CONFIGS + [R.CPU_CONFIG, R.GPU_CONFIG, R.GPU_SMALL_CONFIG])
def test_radix_histogram_and_scatter_pass(rt, cfg):
    """One pass's kernels, each against its reference."""
    rng = np.random.default_rng(11)
    n = 1237
    keys = rng.integers(0, 2 ** 63, n, dtype=np.uint64)
    vals = rng.integers(-5, 5, n).astype(np.int32)
    shift = 7
    items = cfg.items_for(n, rt.compute_units)
    n_blocks = -(-n // (cfg.wg * items))
    radix = 1 << cfg.radix_bits
    q = rt.queue
    dk, dv = cla.to_device(q, keys), cla.to_device(q, vals)
    hist = cla.empty(q, radix * n_blocks, np.int32)
    k_hist = rt.kernel("sort.cl", "radix_histogram", cfg.options())
    no_limits = (rt.dummy_buffer(), np.int32(-1), np.int32(-1))
    k_hist(q, (n_blocks * cfg.wg,), (cfg.wg,), dk.data, np.int32(n), np.int32(items),
           np.int32(shift), np.int32(n_blocks), hist.data, *no_limits)
    ref_hist = radix_histogram_ref(keys, shift, cfg.radix_bits, cfg.wg * items)
    np.testing.assert_array_equal(hist.get().reshape(radix, n_blocks), ref_hist)

    offsets = cla.to_device(q, exclusive_scan_ref(ref_hist.ravel())[0])
    ok, ov = cla.empty(q, n, np.uint64), cla.empty(q, n, np.int32)
    k_sc = rt.kernel("sort.cl", "radix_scatter", cfg.options())
    k_sc(q, (n_blocks * cfg.wg,), (cfg.wg,), dk.data, dv.data, np.int32(n), np.int32(items),
         np.int32(shift), np.int32(n_blocks), offsets.data, ok.data, ov.data, *no_limits)
    ref_k, ref_v = radix_scatter_ref(keys, vals, shift, cfg.radix_bits)
    np.testing.assert_array_equal(ok.get(), ref_k)
    np.testing.assert_array_equal(ov.get(), ref_v)


# --- the whole sort -----------------------------------------------------------------------------

@pytest.mark.parametrize("n", [0, 1, 2, 13, 255, 4095, 4096, 4097, 100_000])
def test_sort_matches_stable_argsort(rt, n):
    rng = np.random.default_rng(n + 1)
    _sort_and_check(rt, _keys(rng, n), num_bits=64)


@pytest.mark.parametrize("cfg", TINY_CONFIGS + [R.GPU_CONFIG, R.GPU_SMALL_CONFIG])
@pytest.mark.parametrize("n", [1, 11, 24, 25, 97, 3000])
def test_sort_block_boundaries_any_config(rt, cfg, n):
    """Sizes around multiples of the block size (wg * items) for several digit widths."""
    rng = np.random.default_rng(n)
    _sort_and_check(rt, _keys(rng, n, n_tiles=7, n_depths=5), num_bits=44, config=cfg)


def test_sort_all_equal_keys_keeps_input_order(rt):
    _sort_and_check(rt, np.full(5000, 12345, np.uint64), num_bits=64)


def test_sort_full_64_bit_keys(rt):
    rng = np.random.default_rng(5)
    keys = rng.integers(0, 2 ** 64 - 1, 20000, dtype=np.uint64, endpoint=True)
    keys[:100] = keys[100:200]  # duplicates
    keys[200] = np.uint64(2 ** 64 - 1)
    keys[201] = 0
    _sort_and_check(rt, keys, num_bits=64)


@pytest.mark.parametrize("num_bits", [1, 5, 32, 33, 43, 44])
def test_sort_only_needed_bits(rt, num_bits):
    """With num_bits, the sort runs ceil(num_bits / radix_bits) passes: keys below 2^num_bits
    come out fully sorted, and bits above the passes' reach are ignored (order by the low bits,
    stable)."""
    rng = np.random.default_rng(num_bits)
    cfg = R.default_config(rt)
    n = 3000
    low = rng.integers(0, 2 ** num_bits, n, dtype=np.uint64)
    low[: n // 2] = low[n // 2:]  # duplicates
    _sort_and_check(rt, low, num_bits=num_bits, config=cfg)

    reach = R.sort_passes(num_bits, cfg.radix_bits) * cfg.radix_bits
    if reach < 64:
        high = rng.integers(1, 2 ** (64 - reach), n, dtype=np.uint64) << np.uint64(reach)
        keys = low | high
        vals = np.arange(n, dtype=np.int32)
        sk, sv = R.radix_sort_pairs(rt, cla.to_device(rt.queue, keys), cla.to_device(rt.queue, vals),
                                    num_bits, cfg)
        order = np.argsort(low, kind="stable")  # low == keys masked to the passes' reach
        np.testing.assert_array_equal(sv.get(), order)
        np.testing.assert_array_equal(sk.get(), keys[order])


def test_sort_passes():
    assert R.sort_passes(44, 8) == 6 and R.sort_passes(44, 4) == 11 and R.sort_passes(48, 8) == 6
    assert R.sort_passes(0, 8) == 0 and R.sort_passes(100, 8) == 8


def test_default_config_by_device_and_size():
    """CPUs get CPU_CONFIG at any size; GPUs the 6-bit configuration below GPU_SMALL_MAX keys and
    the 4-bit one from there (and when the size is not given), each cut to the device's
    work-group and local-memory limits."""
    from types import SimpleNamespace
    cpu = SimpleNamespace(caps=SimpleNamespace(simt=None, max_work_group_size=4096, local_mem_size=1 << 19))
    gpu = SimpleNamespace(caps=SimpleNamespace(simt=32, max_work_group_size=1024, local_mem_size=48 << 10))
    small_gpu = SimpleNamespace(caps=SimpleNamespace(simt=32, max_work_group_size=256, local_mem_size=8 << 10))
    assert R.default_config(cpu, 10) == R.default_config(cpu, 10 ** 8) == R.CPU_CONFIG
    assert R.default_config(gpu, R.GPU_SMALL_MAX - 1) == R.GPU_SMALL_CONFIG
    assert R.default_config(gpu, R.GPU_SMALL_MAX) == R.default_config(gpu) == R.GPU_CONFIG
    for n in (100, 10 ** 8):   # 4 bytes per [digit, work-item] entry in half of 8 KiB
        cfg = R.default_config(small_gpu, n)
        assert cfg.radix_bits == R.default_config(gpu, n).radix_bits
        assert 4 * (1 << cfg.radix_bits) * cfg.wg <= 4 << 10 and cfg.wg * 2 * 4 * (1 << cfg.radix_bits) > 4 << 10


def test_config_for_bits_one_wide_pass_on_cpus(rt):
    """On a CPU, keys of 9 to CPU_ONE_PASS_BITS bits take one pass of that many bits (and sort as
    stable argsort); fewer or more bits, and GPUs, keep the default configuration."""
    from types import SimpleNamespace
    cpu = SimpleNamespace(caps=SimpleNamespace(simt=None, max_work_group_size=4096, local_mem_size=1 << 19))
    gpu = SimpleNamespace(caps=SimpleNamespace(simt=32, max_work_group_size=1024, local_mem_size=48 << 10))
    for bits in range(1, 16):
        cfg = R.config_for_bits(cpu, 1000, bits)
        one = R.CPU_CONFIG.radix_bits < bits <= R.CPU_ONE_PASS_BITS
        assert cfg == (R.CPU_CONFIG if not one else R.SortConfig(**{**vars(R.CPU_CONFIG), "radix_bits": bits}))
        assert R.config_for_bits(gpu, 1000, bits) == R.default_config(gpu, 1000)
    rng = np.random.default_rng(9)
    for bits in (9, R.CPU_ONE_PASS_BITS):
        cfg = R.config_for_bits(rt, 5000, bits)
        keys = rng.integers(0, 1 << bits, small(5000, 300)).astype(np.uint64)
        vals = np.arange(keys.size, dtype=np.int32)
        sk, sv = R.radix_sort_pairs(rt, cla.to_device(rt.queue, keys), cla.to_device(rt.queue, vals), bits, cfg)
        order = np.argsort(keys, kind="stable")
        np.testing.assert_array_equal(sv.get(), vals[order])
        np.testing.assert_array_equal(sk.get(), keys[order])


def test_sort_values_are_arbitrary_payload(rt):
    rng = np.random.default_rng(9)
    n = 7777
    keys = _keys(rng, n)
    vals = rng.integers(-2 ** 31, 2 ** 31 - 1, n).astype(np.int32)
    sk, sv = R.radix_sort_pairs(rt, cla.to_device(rt.queue, keys), cla.to_device(rt.queue, vals), 64)
    ref_k, ref_v = sort_pairs_ref(keys, vals)
    np.testing.assert_array_equal(sk.get(), ref_k)
    np.testing.assert_array_equal(sv.get(), ref_v)


def test_sort_rejects_bad_inputs(rt):
    q = rt.queue
    with pytest.raises(TypeError):
        R.radix_sort_pairs(rt, cla.zeros(q, 4, np.int64), cla.zeros(q, 4, np.int32))
    with pytest.raises(ValueError):
        R.radix_sort_pairs(rt, cla.zeros(q, 4, np.uint64), cla.zeros(q, 3, np.int32))


@pytest.mark.slow
def test_sort_ten_million(rt):
    rng = np.random.default_rng(10)
    _sort_and_check(rt, _keys(rng, 10_000_000, n_tiles=1280, n_depths=100_000), num_bits=43)


@pytest.mark.oclgrind
@pytest.mark.parametrize("cfg", [R.CPU_CONFIG, R.GPU_CONFIG, R.GPU_SMALL_CONFIG, TINY_CONFIGS[0], TINY_CONFIGS[3]])
def test_sort_tiny(rt, cfg):
    rng = np.random.default_rng(1)
    n = small(1000, 1000)
    _sort_and_check(rt, _keys(rng, n, n_tiles=20, n_depths=10), num_bits=37, config=cfg)


# --- limits kept on the device (ops.sort.radix_sort_pairs limits) --------------------------------

def _sort_with_limits(rt, keys, num_bits, config, count=None, bits=None):
    """radix_sort_pairs with the key count and / or key bits in a device array; the first
    min(n, count) sorted pairs against the reference of those keys, the inputs unchanged."""
    q = rt.queue
    n = len(keys)
    vals = np.arange(n, dtype=np.int32)
    lim = cla.to_device(q, np.array([-7, count if count is not None else -1, bits if bits is not None else -1],
                                    np.int32))
    dk, dv = cla.to_device(q, keys), cla.to_device(q, vals)
    sk, sv = R.radix_sort_pairs(rt, dk, dv, num_bits, config, limits=lim, n_at=1 if count is not None else -1,
                                bits_at=2 if bits is not None else -1)
    m = n if count is None else max(0, min(n, count))
    ref_k, ref_v = sort_pairs_ref(keys[:m], vals[:m])
    np.testing.assert_array_equal(sv.get()[:m], ref_v)
    np.testing.assert_array_equal(sk.get()[:m], ref_k)
    np.testing.assert_array_equal(dk.get(), keys)
    np.testing.assert_array_equal(dv.get(), vals)


@pytest.mark.parametrize("cfg", TINY_CONFIGS + [R.CPU_CONFIG, R.GPU_SMALL_CONFIG])
@pytest.mark.parametrize("count", [0, 1, 700, 1999, 2000, 5000])
def test_sort_count_on_the_device(rt, cfg, count):
    """Only the first count keys (clamped to the buffers' 2000) are sorted, the launches sized for
    all of them."""
    rng = np.random.default_rng(count)
    _sort_with_limits(rt, _keys(rng, 2000, n_tiles=50, n_depths=30), 38, cfg, count=count)


@pytest.mark.parametrize("cfg", TINY_CONFIGS + [R.CPU_CONFIG, R.GPU_SMALL_CONFIG])
@pytest.mark.parametrize("bits", [0, 1, 5, 8, 13, 22, 32])
def test_sort_key_bits_on_the_device(rt, cfg, bits):
    """Keys below 2^bits sorted with 32 bits' passes: those at or above bits copy; the same order."""
    rng = np.random.default_rng(bits + 100)
    keys = rng.integers(0, 1 << bits, 1500, dtype=np.uint64) if bits else np.zeros(1500, np.uint64)
    _sort_with_limits(rt, keys, 32, cfg, bits=bits)


def test_sort_count_and_key_bits_together(rt):
    rng = np.random.default_rng(7)
    keys = rng.integers(0, 1 << 11, 3000, dtype=np.uint64)
    _sort_with_limits(rt, keys, 24, TINY_CONFIGS[0], count=2222, bits=11)


@pytest.mark.oclgrind
@pytest.mark.parametrize("cfg", [R.CPU_CONFIG, R.GPU_SMALL_CONFIG, TINY_CONFIGS[0], TINY_CONFIGS[3]])
def test_sort_limits_tiny(rt, cfg):
    rng = np.random.default_rng(2)
    n = small(600, 300)
    keys = rng.integers(0, 1 << 9, n, dtype=np.uint64)
    _sort_with_limits(rt, keys, 32, cfg, count=n - 17, bits=9)
    _sort_with_limits(rt, keys, 32, cfg, count=n + 5)
