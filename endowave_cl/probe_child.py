"""The child's side of the rasterizer probe (probe.py runs ``python -m endowave_cl.probe_child``):
build a vector rasterizer variant, ask for its binaries, run it on a tiny scene and compare it with
the scalar kernels; the last line printed is the verdict."""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from typing import Optional

import numpy as np
import pyopencl.array as cla

from .ops.rasterize import RasterChoice, rasterize, rasterize_bwd, vec_bwd_options, vec_options
from .probe import RESULT_TAG, _last_line, _plant
from .reference.binning import bin_gaussians_ref, bin_offsets_ref, sort_pairs_ref, tile_grid, tile_ranges_ref
from .runtime import KernelBuildError, Runtime, choose_device


def _tiny_scene(C: int, seed: int = 7):
    """24 random screen-space Gaussians over a 36 x 20 image (3 x 2 tiles, partial ones included),
    with their depth-sorted tile lists (numpy binning reference)."""
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
    warnings.filterwarnings("ignore", message="Non-empty compiler output")
    ap = argparse.ArgumentParser(prog="python -m endowave_cl.probe_child",
                                 description="Probe one vector rasterizer variant (run by endowave-cl "
                                             "in a child process).")
    ap.add_argument("--device", required=True)
    ap.add_argument("--channels", type=int, required=True)
    ap.add_argument("--lanes", type=int, required=True)
    ap.add_argument("--block-width", type=int, required=True)
    a = ap.parse_args(argv)
    rt = Runtime(choose_device(a.device))
    try:
        kind, reason = probe_variant(rt, a.channels, a.lanes, a.block_width)
    except Exception as e:   # anything the probe cannot finish counts against the variant
        kind, reason = "error", f"{type(e).__name__}: {_last_line(str(e))}"
    print(RESULT_TAG + json.dumps({"ok": kind == "ok", "kind": kind, "reason": reason}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
