"""numpy references of the radix sort (cl/sort.cl, ops/sort.py): the whole sort (numpy's stable
argsort) and the pieces the tests also check one by one."""
from __future__ import annotations

import numpy as np


def sort_pairs_ref(keys: np.ndarray, values: np.ndarray):
    """(keys, values) ordered by key, ties in input order (what the LSD radix sort gives)."""
    order = np.argsort(keys, kind="stable")
    return keys[order], values[order]


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
