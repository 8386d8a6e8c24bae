"""The host allocator's policy for large temporary arrays.

The in-between targets (train/between.py) and the host halves of a training step make and drop
numpy arrays of a few MB many times per step.  glibc's malloc serves blocks that large with mmap
and returns them to the kernel on free, so every step pays page faults and the kernel's zeroing of
fresh pages again: on the 320x256 pulling frames a forward splat (baselines.splat_forward) took
three times as long as its arithmetic (research/PERFORMANCE.md, "The host allocator").  Raising
malloc's mmap threshold and trim threshold keeps those blocks in the heap for reuse.  Results do
not change, only where the memory comes from; the process keeps its peak working set mapped.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import sys

# mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
# glibc refuses an mmap threshold above HEAP_MAX_SIZE / 2 (32 MiB on 64-bit): blocks up to that
# size (a 640x512 frame's [4, H x W] float64 splat weights are 10.5 MB) come from the heap
MMAP_THRESHOLD = 32 * 1024 * 1024
TRIM_THRESHOLD = 512 * 1024 * 1024   # freed heap memory kept for reuse up to this much

_done = None


def keep_freed_memory() -> bool:
    """Set the thresholds once per process (glibc only; elsewhere nothing is done).  True when
    they are set."""
    global _done
    if _done is not None:
        return _done
    _done = False
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):       # not glibc (musl has no mallopt)
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    _done = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
    return _done
