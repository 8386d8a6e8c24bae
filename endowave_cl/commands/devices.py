"""List the OpenCL platforms and devices; '*' marks the device that would be used."""
from __future__ import annotations

import pyopencl as cl

from ..ops.rasterize import explain_choice
from ..runtime import OpenCLUnavailable, Runtime, build_problem, choose_device, list_devices


def add_arguments(p) -> None:
    p.add_argument("--build-test", action="store_true",
                   help="also build a small kernel on the chosen device to check the toolchain")


def _rasterizer(entry) -> str:
    """The rasterizer variant this device runs for the renderer's 6 channels, and why (the probe
    verdicts of the lane counts tried; a first call probes them in child processes)."""
    try:
        ch, notes, _ = explain_choice(Runtime(entry, disk_cache=True), 6)
    except Exception as ex:   # a device that cannot even make a context
        return f"unavailable ({_one_line(ex)})"
    return f"{ch.describe() if ch else 'none (the forced variant failed)'} ({'; '.join(notes)})"


def _one_line(ex) -> str:
    return (str(ex).strip().splitlines() or [type(ex).__name__])[0]


def run(args) -> int:
    entries = list_devices()
    try:
        chosen, none_builds = choose_device(getattr(args, "device", None), entries), None
    except OpenCLUnavailable as ex:   # every candidate failed its build check: list them all first
        chosen, none_builds = None, ex
    for e in entries:
        d = e.device
        mark = "*" if e is chosen else " "
        kind = "simulator" if e.is_oclgrind else next(
            (n for n, bit in (("GPU", cl.device_type.GPU), ("CPU", cl.device_type.CPU),
                              ("accelerator", cl.device_type.ACCELERATOR)) if d.type & bit), "other")
        print(f"{mark} [{e.index}] {e.platform_index}:{e.device_index}  {e.label}  "
              f"({kind}, {d.max_compute_units} CU, {d.global_mem_size // 2**20} MiB, {d.version.strip()})")
        problem = None if e.is_oclgrind else build_problem(e)
        print(f"      driver {d.driver_version.strip()}; "
              + (f"cannot build kernels ({problem})" if problem else f"rasterizer: {_rasterizer(e)}"))
    if chosen is None:
        raise none_builds
    print(f"\nchosen: [{chosen.index}] {chosen.label}")
    if args.build_test:
        rt = Runtime(chosen)
        rt.program("util.cl")
        print("build test: ok")
    return 0
