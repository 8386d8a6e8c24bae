"""Probing a rasterizer variant in a child process before this process builds it.

A CPU driver can abort the process, hang, or compile wrong code while it generates code for a kernel
(PoCL 3.0 / LLVM 14 on AVX-512 CPUs at 16 lanes: docs/PORTABILITY.md), and asking a program for its
binary, as the disk cache does, is what starts that code generation.  So the first use of a vector
rasterizer variant on a device runs it in a child process with a time limit: the child builds
rasterize_vec.cl and rasterize_vec_bwd.cl (both reduction modes) with the variant's options, asks for
their binaries, runs forward and adjoint on a tiny scene and compares the results with the scalar
kernels.  Only an "ok" lets this process build the variant (ops.rasterize.raster_choice); the
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
    from .runtime import ENV_CACHE_DIR, _default_cache_dir
    from . import env
    cache = env.get(ENV_CACHE_DIR)
    return Path(cache) / "probes" if cache else _default_cache_dir().parent / "probes"


def _plant(vw: int) -> Optional[str]:
    from . import env      # every ENDOWAVE_* variable is parsed there, with a named error
    return (env.get(ENV_PLANT) or {}).get(int(vw))


def _key(rt, C: int, vw: int, bw: int) -> str:
    from .runtime import _source_with_includes_hash
    from .ops.rasterize import RasterChoice, vec_options
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
    from . import env as envvars
    timeout = float(timeout or envvars.get(ENV_TIMEOUT) or DEFAULT_TIMEOUT)
    e = rt.entry
    pkg_root = str(Path(__file__).resolve().parent.parent)
    env = dict(os.environ)
    env["PYTHONPATH"] = pkg_root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env["ENDOWAVE_CL_KERNELS"] = str(rt.kdir)
    cmd = [sys.executable, "-m", "endowave_cl.probe", "--device", f"{e.platform_index}:{e.device_index}",
           "--channels", str(C), "--lanes", str(vw), "--block-width", str(bw)]
    # The child shares the driver's own cache (PoCL: ~/.cache/pocl), so this process then finds the
    # variant compiled; an entry a crash leaves half-written belongs to the failed variant, which
    # this process never builds.
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, env=env, stdin=subprocess.DEVNULL, capture_output=True, text=True,
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


# ----------------------------------------------------------------------------------- the child
def _tiny_scene(C: int, seed: int = 7):
    """24 random screen-space Gaussians over a 36 x 20 image (3 x 2 tiles, partial ones included),
    with their depth-sorted tile lists (numpy binning reference)."""
    import numpy as np
    from .reference.binning import (bin_gaussians_ref, bin_offsets_ref, sort_pairs_ref, tile_grid,
                                    tile_ranges_ref)
    rng = np.random.default_rng(seed)
    n, w, h = 24, 36, 20
    means = np.stack([rng.uniform(-2, w + 2, n), rng.uniform(-2, h + 2, n)], 1)
    s = rng.uniform(1.0, 5.0, (n, 2))
    th = rng.uniform(0, np.pi, n)
    c, si = np.cos(th), np.sin(th)
    R = np.stack([np.stack([c, -si], 1), np.stack([si, c], 1)], 1)
    cov = R @ (s[:, :, None] ** 2 * np.eye(2)[None]) @ np.transpose(R, (0, 2, 1)) + 0.3 * np.eye(2)[None]
    inv = np.linalg.inv(cov)
    conic = np.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], 1)
    radius = np.ceil(3 * np.sqrt(np.linalg.eigvalsh(cov)[:, -1])).astype(np.int32)
    tx, ty = tile_grid(w, h)
    rect = np.stack([np.floor((means[:, 0] - radius) / 16), np.floor((means[:, 1] - radius) / 16),
                     np.ceil((means[:, 0] + radius) / 16), np.ceil((means[:, 1] + radius) / 16)], 1)
    rect = np.clip(rect, 0, [tx, ty, tx, ty]).astype(np.int32)
    empty = (rect[:, 2] <= rect[:, 0]) | (rect[:, 3] <= rect[:, 1])   # off screen: culled, as binning does
    radius[empty] = 0
    rect[empty] = 0
    depth = rng.uniform(0.5, 5.0, n).astype(np.float32)
    keys, vals = bin_gaussians_ref(rect, depth, radius, tx)
    skeys, svals = sort_pairs_ref(keys, vals)
    arrays = dict(means2d=means.astype(np.float32), conic=conic.astype(np.float32),
                  opac=rng.uniform(0.3, 1.0, n).astype(np.float32),
                  features=rng.uniform(-1, 1, (n, C)).astype(np.float32),
                  sorted_values=svals.astype(np.int32), tile_ranges=tile_ranges_ref(skeys, tx * ty))
    v_out = rng.standard_normal((h, w, C)).astype(np.float32)
    v_alpha = rng.standard_normal((h, w)).astype(np.float32)
    return arrays, w, h, v_out, v_alpha, rect, bin_offsets_ref(rect, radius)


def _mismatch(name: str, got, want, rtol: float) -> Optional[str]:
    import numpy as np
    if got.shape != want.shape or not np.isfinite(got).all():
        return f"{name}: wrong shape or non-finite values"
    scale = max(float(np.abs(want).max()), 1e-6)
    err = float(np.abs(got.astype(np.float64) - want).max()) if got.size else 0.0
    if err > rtol * scale + rtol * 1e-3:
        return f"{name} differs from the scalar kernel by {err:.3g} (scale {scale:.3g})"
    return None


def probe_variant(rt, C: int, vw: int, bw: int):
    """Build the vector variant, ask for its binaries, run it on the tiny scene and compare with the
    scalar kernels.  (kind, reason): ("ok", "ok"), ("build", ...) or ("wrong", ...)."""
    import numpy as np
    import pyopencl.array as cla
    from .ops.rasterize import (RasterChoice, rasterize, rasterize_bwd, vec_bwd_options, vec_options)
    from .runtime import KernelBuildError
    plant = _plant(vw)
    if plant == "abort":
        os.abort()
    if plant == "hang":
        while True:
            time.sleep(60)
    ch = RasterChoice("vector", vw, bw)
    programs = [("rasterize_vec.cl", vec_options(C, ch))] + [
        ("rasterize_vec_bwd.cl", vec_bwd_options(rt, C, ch, det)) for det in (False, True)]
    try:
        if plant == "build":
            rt.program("rasterize_vec.cl", vec_options(C, ch), source="__kernel void k(void) { planted }")
        for f, opts in programs:
            prg = rt.program(f, opts)
            prg.get_info(rt.cl.program_info.BINARIES)   # what makes PoCL generate code
    except KernelBuildError as e:
        return "build", "build failed: " + _last_line(str(e))
    arrays, w, h, v_out, v_alpha, rect, offsets = _tiny_scene(C)
    q = rt.queue
    dev = [cla.to_device(q, np.ascontiguousarray(arrays[n])) for n in
           ("means2d", "conic", "opac", "features", "sorted_values", "tile_ranges")]
    vo, va = cla.to_device(q, v_out), cla.to_device(q, v_alpha)
    det = (cla.to_device(q, rect), cla.to_device(q, offsets))
    results = {}
    for name, c in (("vector", ch), ("scalar", RasterChoice("scalar"))):
        r = rasterize(rt, *dev, w, h, choice=c)
        g = rasterize_bwd(rt, *dev, w, h, r, vo, va, choice=c)
        gd = rasterize_bwd(rt, *dev, w, h, r, vo, va, deterministic=det, choice=c)
        results[name] = dict(out=r.out.get(), alpha=r.alpha.get(), T_final=r.T_final.get(), last=r.last.get(),
                             **{k: x.get() for k, x in g.items()},
                             **{"det_" + k: x.get() for k, x in gd.items()})
    got, want = results["vector"], results["scalar"]
    if plant == "wrong":
        got["out"][0, 0, 0] += 1.0
    if not np.array_equal(got["last"], want["last"]):
        return "wrong", f"last differs from the scalar kernel at {int((got['last'] != want['last']).sum())} pixels"
    for k in want:
        if k == "last":
            continue
        bad = _mismatch(k, got[k], want[k], 1e-4 if k in ("out", "alpha", "T_final") else 2e-3)
        if bad:
            return "wrong", bad
    return "ok", "ok"


def main(argv=None) -> int:
    import argparse
    import warnings
    warnings.filterwarnings("ignore", message="Non-empty compiler output")
    ap = argparse.ArgumentParser(prog="python -m endowave_cl.probe",
                                 description="Probe one vector rasterizer variant (run by endowave-cl "
                                             "in a child process).")
    ap.add_argument("--device", required=True)
    ap.add_argument("--channels", type=int, required=True)
    ap.add_argument("--lanes", type=int, required=True)
    ap.add_argument("--block-width", type=int, required=True)
    a = ap.parse_args(argv)
    from .runtime import Runtime, choose_device
    rt = Runtime(choose_device(a.device))
    try:
        kind, reason = probe_variant(rt, a.channels, a.lanes, a.block_width)
    except Exception as e:   # anything the probe cannot finish counts against the variant
        kind, reason = "error", f"{type(e).__name__}: {_last_line(str(e))}"
    print(RESULT_TAG + json.dumps({"ok": kind == "ok", "kind": kind, "reason": reason}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
