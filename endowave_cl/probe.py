"""Probing a rasterizer variant in a child process before this process builds it.

A CPU driver can abort the process, hang, or compile wrong code while it generates code for a kernel
(PoCL 3.0 / LLVM 14 on AVX-512 CPUs at 16 lanes: docs/PORTABILITY.md), and asking a program for its
binary, as the disk cache does, is what starts that code generation.  So the first use of a vector
rasterizer variant on a device runs it in a child process with a time limit: the child builds
rasterize_vec.cl and rasterize_vec_bwd.cl (both reduction modes) with the variant's options, asks for
their binaries, runs forward and adjoint on a tiny scene and compares the results with the scalar
kernels (the child's side: endowave_cl/probe_child.py).  Only an "ok" lets this process build the variant (ops.rasterize.raster_choice); the
child's build has by then written the disk cache, so this process loads it instead of compiling.

The verdict is cached as JSON in the probes folder beside the program cache
(``~/.cache/endowave-cl/probes``, or ``$ENDOWAVE_CL_CACHE/probes``), keyed by device, driver version,
kernel sources with their includes, and build options: a warm start reads one small file.

Environment: ENDOWAVE_PROBE_TIMEOUT (seconds a child may take, default 120).  For tests,
ENDOWAVE_PROBE_PLANT="16=abort,8=hang,4=build,2=wrong" makes the child of that lane count abort,
hang, fail to build or return wrong values (it is part of the verdict's key).
"""
from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Optional

from . import env      # every ENDOWAVE_* variable is parsed there, with a named error
from .ops.raster_options import RasterChoice, vec_options
from .runtime import ENV_CACHE_DIR, _default_cache_dir, _source_with_includes_hash

ENV_TIMEOUT = "ENDOWAVE_PROBE_TIMEOUT"
ENV_PLANT = "ENDOWAVE_PROBE_PLANT"
DEFAULT_TIMEOUT = 120.0
RESULT_TAG = "endowave-probe-result "
KERNEL_FILES = ("rasterize_vec.cl", "rasterize_vec_bwd.cl")


@dataclass
class Verdict:
    ok: bool
    reason: str           # "ok", or what went wrong, one line
    seconds: float        # the child's wall time
    kind: str = "ok"      # ok | wrong (built, ran, mismatched) | build | crash | hang | error
    cached: bool = False  # read from the probes folder


def probe_dir() -> Path:
    cache = env.get(ENV_CACHE_DIR)
    return Path(cache) / "probes" if cache else _default_cache_dir().parent / "probes"


def _plant(vw: int) -> Optional[str]:
    return (env.get(ENV_PLANT) or {}).get(int(vw))


def _key(rt, C: int, vw: int, bw: int) -> str:
    h = hashlib.sha256()
    for f in KERNEL_FILES:
        _source_with_includes_hash(rt.kdir / f, h)
    d = rt.device
    opts = vec_options(C, RasterChoice("vector", vw, bw))
    h.update("\0".join([*opts, d.name, d.platform.name, d.version, d.driver_version,
                        str(rt.local_mem_size), _plant(vw) or ""]).encode())
    return h.hexdigest()[:32]


_MEMO: Dict[str, Verdict] = {}


def verdict(rt, C: int, vw: int, bw: int, timeout: Optional[float] = None) -> Verdict:
    """The probe verdict of the vector rasterizer with vw lanes in bw-wide blocks and C channels on
    rt's device: from memory, else the probes folder, else a child process (then cached)."""
    key = _key(rt, C, vw, bw)
    v = _MEMO.get(key)
    if v is not None:
        return v
    f = probe_dir() / f"raster-{key}.json"
    try:
        d = json.loads(f.read_text())
        v = Verdict(bool(d["ok"]), str(d["reason"]), float(d["seconds"]), str(d["kind"]), cached=True)
    except Exception:   # absent or unreadable: probe again
        timed = getattr(rt, "timed_build", None)     # the probe's time is build time (runtime.py)
        if timed is None:
            v = run_child(rt, C, vw, bw, timeout)
        else:
            with timed(f"the {vw}-lane rasterizer probe"):
                v = run_child(rt, C, vw, bw, timeout)
        try:
            f.parent.mkdir(parents=True, exist_ok=True)
            tmp = f.with_suffix(f".tmp{os.getpid()}")
            tmp.write_text(json.dumps({"ok": v.ok, "kind": v.kind, "reason": v.reason,
                                       "seconds": round(v.seconds, 3),
                                       "device": rt.name, "driver": rt.device.driver_version,
                                       "lanes": vw, "block_width": bw, "channels": C}))
            os.replace(tmp, f)
        except OSError:
            pass   # a read-only cache: probe again next time
    _MEMO[key] = v
    return v


def _last_line(text: str) -> str:
    lines = [ln.strip() for ln in (text or "").splitlines() if ln.strip()]
    return lines[-1][:200] if lines else ""


def run_child(rt, C: int, vw: int, bw: int, timeout: Optional[float] = None) -> Verdict:
    """Run the probe of one variant in a child process; never raises for what the child does."""
    timeout = float(timeout or env.get(ENV_TIMEOUT) or DEFAULT_TIMEOUT)
    e = rt.entry
    pkg_root = str(Path(__file__).resolve().parent.parent)
    child_env = dict(os.environ)
    child_env["PYTHONPATH"] = pkg_root + (os.pathsep + child_env["PYTHONPATH"] if child_env.get("PYTHONPATH") else "")
    child_env["ENDOWAVE_CL_KERNELS"] = str(rt.kdir)
    cmd = [sys.executable, "-m", "endowave_cl.probe_child", "--device", f"{e.platform_index}:{e.device_index}",
           "--channels", str(C), "--lanes", str(vw), "--block-width", str(bw)]
    # The child shares the driver's own cache (PoCL: ~/.cache/pocl), so this process then finds the
    # variant compiled; an entry a crash leaves half-written belongs to the failed variant, which
    # this process never builds.
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, env=child_env, stdin=subprocess.DEVNULL, capture_output=True, text=True,
                           timeout=timeout, start_new_session=True)
    except subprocess.TimeoutExpired:
        return Verdict(False, f"no answer within {timeout:.0f} s (a hang while building?)",
                       time.perf_counter() - t0, "hang")
    except OSError as ex:
        return Verdict(False, f"could not start the probe: {ex}", time.perf_counter() - t0, "error")
    dt = time.perf_counter() - t0
    for line in reversed(p.stdout.splitlines()):
        if line.startswith(RESULT_TAG):
            d = json.loads(line[len(RESULT_TAG):])
            return Verdict(bool(d["ok"]), str(d["reason"]), dt, str(d["kind"]))
    why = _last_line(p.stderr)
    if p.returncode < 0:
        try:
            sig = signal.Signals(-p.returncode).name
        except ValueError:
            sig = f"signal {-p.returncode}"
        what = f"the driver killed the process ({sig})"
    else:
        what = f"the probe exited with code {p.returncode}"
    return Verdict(False, what + (f": {why}" if why else ""), dt, "crash")


if __name__ == "__main__":
    # ``python -m endowave_cl.probe`` was the child's command before the child's side moved to
    # probe_child.py: a process started before that update still runs it, and must get a verdict
    import runpy
    runpy.run_module("endowave_cl.probe_child", run_name="__main__")
