"""OpenCL runtime: one :class:`Runtime` per device, with a context, an in-order queue, the
programs built for it and the per-device state of the ops.

The parts around it: device.py lists the devices and chooses one (and what it can do,
DeviceCaps); program_cache.py finds the kernel sources and keeps built programs on disk.  Kernels
are built with the kernel folder on the include path, so ``#include "common.h"`` works from any
kernel file.  The names of both parts are importable from here as before.
"""
from __future__ import annotations

import contextlib
import hashlib
import math
import threading
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from . import env
from .device import (ENV_DEVICE, ENV_OCLGRIND, NO_PLATFORM_HELP, UNKNOWN_CPU_HELP,  # noqa: F401  (re-exported)
                     DeviceCaps, DeviceEntry, OpenCLUnavailable, _cl, build_problem, choose_device,
                     list_devices, oclgrind_mode, query_caps)
from .program_cache import (ENV_CACHE_DIR, ENV_KERNEL_DIR, ENV_NO_DISK_CACHE, _CACHE_MAGIC,  # noqa: F401
                            _default_cache_dir, _kernel_names, _read_cache_entry,
                            _source_with_includes_hash, _write_cache_entry, cache_key, kernel_dir)


class KernelBuildError(RuntimeError):
    """A kernel file failed to compile; the message holds the build log."""



class Runtime:
    """A context + queue on one device, a cache of built programs, and the per-device state of the
    ops: one memory pool (:meth:`pool`), one empty-buffer placeholder (:meth:`dummy_buffer`,
    :meth:`buf`) and a cache of device constants and per-device choices (:meth:`cached`).  All of
    it lives and dies with the Runtime."""

    def __init__(self, entry: DeviceEntry, disk_cache: Optional[bool] = None):
        cl = _cl()
        self.cl = cl
        self.entry = entry
        self.device = entry.device
        self.ctx = cl.Context([entry.device])
        self.queue = cl.CommandQueue(self.ctx)
        self.kdir = kernel_dir()
        if disk_cache is None:
            disk_cache = not env.flag(ENV_NO_DISK_CACHE) and not entry.is_oclgrind
        self.disk_cache = disk_cache
        self._programs: Dict[Tuple[str, str], object] = {}
        self._kernels: Dict[Tuple[str, str, str], object] = {}
        self._lock = threading.Lock()
        self.cache: Dict[object, object] = {}   # see cached()
        self._pool = None
        self._dummy = None
        # seconds spent building or loading programs (and probing variants, probe.py), so that a
        # run can report them apart from its training time; build_notice(what), when set, is
        # called once, before the first program built from source (a cold cache)
        self.build_seconds = 0.0
        self.build_notice = None

    # -- what kernels need to size themselves -------------------------------------------------
    @property
    def name(self) -> str:
        return self.entry.label

    @property
    def search_text(self) -> str:
        """What a device name spec is matched against (DeviceEntry.search_text)."""
        return self.entry.search_text

    @property
    def is_oclgrind(self) -> bool:
        return self.entry.is_oclgrind

    @property
    def is_gpu(self) -> bool:
        return self.entry.is_gpu

    @property
    def caps(self) -> DeviceCaps:
        """The device queries the build options and launch shapes are chosen from (DeviceCaps)."""
        c = self.cache.get("runtime.caps")
        if c is None:
            c = self.cache["runtime.caps"] = query_caps(self.device)
        return c

    @property
    def compute_units(self) -> int:
        return int(self.device.max_compute_units)

    @property
    def local_mem_size(self) -> int:
        return int(self.device.local_mem_size)

    @property
    def max_work_group_size(self) -> int:
        return int(self.device.max_work_group_size)

    # -- per-device state of the ops ------------------------------------------------------------
    def pool(self):
        """The memory pool of this device's output and gradient buffers: they are reused across
        calls once the previous call's arrays are freed (a fresh 60 MB buffer per call costs more
        than the kernel on PoCL, which allocates and faults in new buffers on first use).  Pass it
        as ``allocator=`` to pyopencl.array.empty; pooled buffers are not zeroed."""
        if self._pool is None:
            from pyopencl.tools import ImmediateAllocator, MemoryPool   # on first device use (device._cl)
            self._pool = MemoryPool(ImmediateAllocator(self.queue))
        return self._pool

    def empty(self, shape, dtype=np.float32):
        """A device array from :meth:`pool` (not zeroed), C-contiguous, of this shape (an int or a
        tuple) and dtype.  The same array as ``pyopencl.array.empty(queue, shape, dtype,
        allocator=rt.pool())``, made without pyopencl's per-call checks of the shape (about 40 us
        a call on the CPU, against 5 us here; a training step makes about a hundred)."""
        return new_array(self.queue, _as_shape(shape), dtype, allocator=self.pool())

    def dummy_buffer(self):
        """A 4-byte placeholder for kernel arguments that are absent or empty (pyopencl gives
        zero-size arrays no buffer); kernels never touch it."""
        if self._dummy is None:
            self._dummy = self.cl.Buffer(self.ctx, self.cl.mem_flags.READ_WRITE, 4)
        return self._dummy

    def buf(self, arr):
        """arr's buffer, or the placeholder when arr is None or empty."""
        return arr.data if arr is not None and arr.size > 0 else self.dummy_buffer()

    def launch(self, kernel, global_size, local_size, *args):
        """Enqueue kernel on this runtime's queue over global_size, in work-groups of local_size
        (None: the driver chooses)."""
        return kernel(self.queue, global_size, local_size, *args)

    def launch_1d(self, kernel, n: int, group: int, *args):
        """One work-item per element of n in work-groups of ``group``: the range is n rounded up to
        a multiple of group, and the kernel checks its index against n."""
        return kernel(self.queue, (round_up(n, group),), (group,), *args)

    def cached(self, key, make):
        """self.cache[key], made by make() on first use: device constants (filters, windows) and
        per-device choices, keyed by the op's name and its parameters."""
        v = self.cache.get(key)
        if v is None:
            v = self.cache[key] = make()
        return v

    def describe(self) -> str:
        d = self.device
        return (f"{self.name} ({d.version.strip()}, {self.compute_units} compute units, "
                f"{self.local_mem_size // 1024} KiB local memory, max work-group {self.max_work_group_size}; "
                f"{self.caps.describe()})")

    # -- building -----------------------------------------------------------------------------
    def _options(self, options: Sequence[str]) -> List[str]:
        caps = self.caps
        return ["-I", str(self.kdir), f"-cl-std={caps.cl_std}", *caps.build_options(), *options]

    def _cache_key(self, path: Path, options: Sequence[str]) -> str:
        return cache_key(path, options, self.device, self.caps)

    def cache_file(self, filename: str, options: Sequence[str] = ()) -> Path:
        """The disk-cache file of cl/<filename> built with ``options`` on this device."""
        path = self.kdir / filename
        return _default_cache_dir() / f"{path.stem}-{self._cache_key(path, tuple(str(o) for o in options))}.bin"

    @contextlib.contextmanager
    def timed_build(self, what: str):
        """Count the block's seconds in build_seconds; the first one calls build_notice(what)."""
        notice, self.build_notice = self.build_notice, None
        if notice is not None:
            notice(what)
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.build_seconds += time.perf_counter() - t0

    def program(self, filename: str, options: Sequence[str] = (), source: Optional[str] = None):
        """Build (or fetch from cache) the program in cl/<filename>.

        ``source`` overrides the file's text (used by tests that plant faults); it is
        then cached in memory only.  A disk-cache entry is used only when its header names this
        build (the cache key), its checksum matches and the loaded program has the kernels the
        header lists; anything else is rebuilt from source and rewritten.
        """
        cl = self.cl
        path = self.kdir / filename
        opts = tuple(str(o) for o in options)
        mem_key = (filename if source is None else "src:" + hashlib.sha256(source.encode()).hexdigest(),
                   " ".join(opts))
        with self._lock:
            prg = self._programs.get(mem_key)
            if prg is not None:
                return prg
            if source is None:
                if not path.is_file():
                    raise FileNotFoundError(f"kernel file {path} does not exist")
                text = path.read_text()
            else:
                text = source
            full_opts = self._options(opts)
            prg = None
            cache_file = key = None
            if self.disk_cache and source is None:
                key = self._cache_key(path, opts)
                cache_file = _default_cache_dir() / f"{path.stem}-{key}.bin"
                if cache_file.is_file():
                    t0 = time.perf_counter()
                    prg = self._load_cached(cache_file, key, full_opts)
                    self.build_seconds += time.perf_counter() - t0
            if prg is None:
                prg = cl.Program(self.ctx, text)
                try:
                    with self.timed_build(filename):
                        prg.build(options=full_opts)
                except cl.Error as e:  # RuntimeError subclasses included
                    try:
                        log = prg.get_build_info(self.device, cl.program_build_info.LOG)
                    except Exception:
                        log = ""
                    log = (log or "").strip() or str(e)
                    if "unknown target cpu" in log.lower():
                        log += "\n" + UNKNOWN_CPU_HELP
                    raise KernelBuildError(
                        f"failed to build OpenCL kernel file {path if source is None else '<source of ' + filename + '>'}"
                        f" for {self.name} with options {' '.join(opts) or '(none)'}\n--- build log ---\n{log}"
                    ) from None
                if cache_file is not None:
                    try:
                        binary = prg.get_info(cl.program_info.BINARIES)[0]
                        if binary:
                            _write_cache_entry(cache_file, key, bytes(binary), _kernel_names(prg))
                    except Exception:
                        pass  # the cache is an optimisation only
            self._programs[mem_key] = prg
            return prg

    def _load_cached(self, cache_file: Path, key: str, full_opts: List[str]):
        """The program in a disk-cache entry, or None (entry removed) when it is not one we wrote
        for this build or does not load."""
        cl = self.cl
        try:
            binary, kernels = _read_cache_entry(cache_file, key)
            prg = cl.Program(self.ctx, [self.device], [binary])
            prg.build(options=full_opts)
            missing = set(kernels) - set(_kernel_names(prg))
            if missing:
                raise ValueError(f"kernels {sorted(missing)} missing after loading")
            return prg
        except Exception:
            try:
                cache_file.unlink()
            except OSError:
                pass
            return None

    def kernel(self, filename: str, name: str, options: Sequence[str] = ()):
        """A kernel object from cl/<filename>; cached, so set its args right before enqueueing."""
        key = (filename, name, " ".join(str(o) for o in options))
        k = self._kernels.get(key)
        if k is None:
            prg = self.program(filename, options)
            if name not in _kernel_names(prg):
                raise KernelBuildError(
                    f"kernel {name} is missing from {self.kdir / filename} as built by {self.name} "
                    f"(kernels: {', '.join(_kernel_names(prg)) or 'none'}); a stale driver cache can do "
                    f"this: clear {_default_cache_dir()} and the driver's cache (PoCL: ~/.cache/pocl)")
            k = getattr(prg, name)
            self._kernels[key] = k
        return k

    def finish(self) -> None:
        self.queue.finish()



_RUNTIMES: Dict[Tuple[int, int], Runtime] = {}


def get_runtime(spec: Optional[str] = None) -> Runtime:
    """The shared Runtime for the device that ``spec`` (or the defaults) selects."""
    entry = choose_device(spec)
    key = (entry.platform_index, entry.device_index)
    rt = _RUNTIMES.get(key)
    if rt is None:
        rt = Runtime(entry)
        _RUNTIMES[key] = rt
    return rt


def _as_shape(shape) -> Tuple[int, ...]:
    """An int or a sequence of ints as a tuple of Python ints."""
    return (int(shape),) if isinstance(shape, (int, np.integer)) else tuple(int(s) for s in shape)


def _c_strides(shape: Tuple[int, ...], itemsize: int) -> Tuple[int, ...]:
    strides, step = [], itemsize
    for n in reversed(shape):
        strides.append(step)
        step *= max(n, 1)
    return tuple(reversed(strides))


_FAST_ARRAYS = [True]   # pyopencl's fast constructor path (Array(..., _fast=True)) is available


def new_array(queue, shape: Tuple[int, ...], dtype, allocator=None, data=None, offset: int = 0,
              events=None):
    """A C-contiguous pyopencl Array of a shape of non-negative ints: new memory from allocator
    (data None), or a view of data at byte offset (sharing ``events``).  Uses pyopencl's own fast
    constructor path, which skips the shape checks that make ``Array(...)`` cost tens of
    microseconds; falls back to the checked constructor where a pyopencl lacks it."""
    import pyopencl.array as cla     # on first device use (device._cl): cli.py imports this module
    dtype = np.dtype(dtype)
    size = math.prod(shape)
    if _FAST_ARRAYS[0]:
        try:
            return cla.Array(None, shape, dtype, allocator=allocator, data=data, offset=offset,
                             strides=_c_strides(shape, dtype.itemsize), events=events, _fast=True,
                             _size=size, _context=queue.context, _queue=queue)
        except TypeError:
            _FAST_ARRAYS[0] = False
    return cla.Array(queue, shape, dtype, allocator=allocator, data=data, offset=offset, events=events)


def view(arr, shape):
    """arr (a C-contiguous pyopencl Array) seen with another shape of the same size: no copy, the
    same memory and events.  What ``arr.reshape(shape)`` gives, without its per-call checks; a
    non-contiguous arr or a size that differs raises ValueError."""
    shape = _as_shape(shape)
    if math.prod(shape) != arr.size:
        raise ValueError(f"view: cannot see {arr.size} elements as {shape}")
    if tuple(arr.strides) != _c_strides(tuple(arr.shape), arr.dtype.itemsize) and arr.size > 1:
        raise ValueError("view: the array is not C-contiguous")
    return new_array(arr.queue, shape, arr.dtype, allocator=arr.allocator, data=arr.base_data,
                     offset=arr.offset, events=arr.events)


def round_up(n: int, m: int) -> int:
    return ((int(n) + m - 1) // m) * m
