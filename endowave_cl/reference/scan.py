"""numpy references of the scan and radix-sort building blocks (cl/scan.cl, cl/sort.cl).

The whole sort's reference is ``sort_pairs_ref`` in reference/binning.py (numpy's stable
argsort); these cover the pieces the tests also check one by one.
"""
from __future__ import annotations

from typing import Tuple

import numpy as np


def exclusive_scan_ref(x: np.ndarray) -> Tuple[np.ndarray, int]:
    """(offsets [n] int32, total) with offsets[k] = sum_{j<k} x[j] (int32 wrap-around)."""
    x = np.asarray(x, np.int32)
    c = np.cumsum(x, dtype=np.int64)
    offsets = np.zeros(len(x), np.int64)
    offsets[1:] = c[:-1]
    total = int(c[-1]) if len(x) else 0
    return offsets.astype(np.int32), total


def radix_histogram_ref(keys: np.ndarray, shift: int, radix_bits: int, block: int) -> np.ndarray:
    """[radix, n_blocks] int32: how many keys of each block of ``block`` keys have each digit
    (bits shift .. shift + radix_bits - 1), digit-major as the kernel writes it."""
    radix = 1 << radix_bits
    n = len(keys)
    n_blocks = (n + block - 1) // block
    digits = ((np.asarray(keys, np.uint64) >> np.uint64(shift)) & np.uint64(radix - 1)).astype(np.int64)
    blocks = np.arange(n) // block
    hist = np.zeros((radix, n_blocks), np.int64)
    np.add.at(hist, (digits, blocks), 1)
    return hist.astype(np.int32)


def radix_scatter_ref(keys: np.ndarray, values: np.ndarray, shift: int, radix_bits: int):
    """One stable LSD pass: (keys, values) ordered by the digit at ``shift``, ties in input order."""
    radix = 1 << radix_bits
    digits = (np.asarray(keys, np.uint64) >> np.uint64(shift)) & np.uint64(radix - 1)
    order = np.argsort(digits, kind="stable")
    return keys[order], values[order]
