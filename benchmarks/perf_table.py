#!/usr/bin/env python
"""Per-kernel time, bytes moved, flops and roofline position of one forward + backward render.

Runs the benchmark scene of benchmarks/bench_render.py (100,000 Gaussians, 640x512, C = 6) on a profiling
queue: every kernel launched through the Runtime is timed by its OpenCL event (median over --runs
after --warmup).  For each kernel it prints the bytes moved and the flops, both *estimated* from
the sizes of this frame (the formulas are in KERNELS below: compulsory traffic, each array read or
written once, gathers counted by their entries; flops by hand count per element), the achieved
GB/s and GFLOP/s and their fraction of the measured peaks of benchmarks/peak_probe.py (--peaks JSON, or
measured now).  --markdown writes the table, --png a roofline-style figure (arithmetic intensity vs
achieved GFLOP/s under the measured bandwidth and FMA roofs).

    python benchmarks/perf_table.py [--device SPEC] [--runs 5] [--peaks peaks.json]
                               [--markdown table.md] [--png research/figures/roofline.png]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from collections import defaultdict

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, HERE)

# flops per element, hand counts (see research/PERFORMANCE.md)
PROJECT_FLOPS = 1100        # per visible Gaussian: rotation, Sigma, conditional, EWA, SH 16 x 9 sums, TEASH, flow
PROJECT_BWD_FLOPS = 1700    # per visible Gaussian: the geometry again + its chain rule + v_sh
FWD_LANE_FLOPS = 48         # per (pixel, Gaussian) evaluation: power 8, exp 20, alpha 4, blend 2C + 4
BWD_LANE_FLOPS = 110        # per (pixel, Gaussian) evaluation of the adjoint: the above + 6C + 30 terms + sums


def stage_of(name: str) -> str:
    if name.startswith("project4d_bwd"):
        return "project_bwd"
    if name.startswith("project4d"):
        return "project"
    if name.startswith(("bin_", "scan_", "radix_", "tile_ranges", "depth_keys", "counts_in_order")):
        return "bin_sort"
    if "_bwd" in name:
        return "rasterize_bwd"
    return "rasterize"


def lane_evaluations(raster, binned, proj, width, height, C):
    """(forward, backward) (pixel, Gaussian) evaluations of the vector rasterizer, from this frame:
    per tile entry, the 4 x 4 pixel blocks its cull box reaches, counted up to the block's largest
    `last` (forward) or the tile's (backward), x 16 lanes.  An estimate of the lanes walked."""
    from endowave_cl.layout import TILE
    rec = raster.rec
    if rec is None:
        return None, None
    box = rec.get()[:, 1, :]                       # (xmin, xmax, ymin, ymax)
    sv = binned.sorted_values.get()
    tr = binned.tile_ranges.get()
    last = raster.last.get()
    tx_n = -(-width // TILE)
    ty_n = -(-height // TILE)
    lastp = np.zeros((ty_n * TILE, tx_n * TILE), np.int64)
    lastp[:height, :width] = last
    # per tile and 4x4 block: max last; per tile: max last
    blk = lastp.reshape(ty_n, TILE // 4, 4, tx_n, TILE // 4, 4).max(axis=(2, 5))   # [ty, by, tx, bx]
    blk = blk.transpose(0, 2, 1, 3).reshape(ty_n * tx_n, (TILE // 4) ** 2)
    tile_max = blk.max(axis=1)
    counts = tr[:, 1] - tr[:, 0]
    tile_of = np.repeat(np.arange(len(tr)), np.maximum(counts, 0))
    starts = np.repeat(tr[:, 0], np.maximum(counts, 0))
    j = np.arange(len(tile_of)) - (np.cumsum(np.maximum(counts, 0)) - np.maximum(counts, 0))[tile_of]
    del starts
    g = sv[tr[tile_of, 0] + j]
    b = box[g]
    tx = tile_of % tx_n
    ty = tile_of // tx_n
    fwd = bwd = 0
    for s in range((TILE // 4) ** 2):
        bx0 = tx * TILE + (s % 4) * 4 + 0.5
        by0 = ty * TILE + (s // 4) * 4 + 0.5
        hit = (b[:, 0] <= bx0 + 3) & (b[:, 1] >= bx0) & (b[:, 2] <= by0 + 3) & (b[:, 3] >= by0)
        fwd += int((hit & (j < blk[tile_of, s])).sum())
        bwd += int((hit & (j < tile_max[tile_of])).sum())
    return 16 * fwd, 16 * bwd


def estimates(name, s):
    """(bytes, flops) of one launch-set of kernel `name` for sizes s (None: not estimated)."""
    N, V, M, P, C, K = s["N"], s["visible"], s["M"], s["pixels"], s["C"], s["sh_floats"]
    NV = 6 + C
    rec = 16 * (3 + (C + 3) // 4)
    # bin_and_sort's two sorts: depth passes over the N Gaussians, tile passes over the M entries
    sorted_elems = s.get("depth_passes", 0) * N + s.get("tile_passes", 0) * M
    table = {
        "project4d": (N * (4 * 16 + 4 + 12) + V * 4 * K + N * (8 + 12 + 4 + 4 + 4 + 4 * C + 16 + 4) + V * 36,
                      V * PROJECT_FLOPS),
        "project4d_bwd": (N * (4 * 16 + 4 + 12 + 4) + V * (36 + 4 * (6 + C)) + N * (4 * 16 + 4 + 4 * K + 12),
                          V * PROJECT_BWD_FLOPS),
        "bin_counts": (N * 16, N),
        "scan_blocks": (N * 8, N), "scan_add_offsets": (N * 8, N),
        "depth_keys": (N * (4 + 4 + 8 + 4), N),
        "counts_in_order": (N * 12, 0),
        "bin_in_order": (N * (4 + 8 + 16) + M * 12, M * 4),
        "radix_histogram": (sorted_elems * 8, sorted_elems * 3),
        "radix_scatter": (sorted_elems * 24, sorted_elems * 4),
        "tile_ranges": (M * 8 + s["tiles"] * 8, M * 2),
        "rasterize_vec_prep": (N * (8 + 12 + 4 + 4 * C) + N * rec, N * 20),
        "rasterize_vec": (M * (4 + rec) + P * 4 * (C + 3), (s["lanes_fwd"] or 0) * FWD_LANE_FLOPS),
        "rasterize_vec_bwd": (M * (4 + rec + (16 + 8 if s["det"] else 0)) + P * 4 * (C + 3)
                              + (M * NV * 4 if s["det"] else N * NV * 4),
                              (s["lanes_bwd"] or 0) * BWD_LANE_FLOPS),
        "rasterize_bwd_gather": (M * NV * 4 + M * 4 + N * 4 + N * NV * 4, M * NV),
        "rasterize_bwd_entry_of": (M * (4 + 16 + 8 + 4) + s["tiles"] * 8, M * 4),
    }
    return table.get(name, (None, None))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None)
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=512)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--peaks", default=None, help="JSON of benchmarks/peak_probe.py (default: measure now)")
    ap.add_argument("--markdown", default=None)
    ap.add_argument("--png", default=None)
    args = ap.parse_args(argv)

    import pyopencl.array as cla

    from bench_render import FOCAL, tissue_scene
    from kernel_events import kernel_ms, profile_launches
    from endowave_cl.camera import Camera
    from endowave_cl.gaussians import upload
    from endowave_cl.ops.binning import DEPTH_BITS, key_bits
    from endowave_cl.ops.sort import config_for_bits, sort_passes
    from endowave_cl.render import render, render_backward
    from endowave_cl.runtime import Runtime, choose_device

    rt = Runtime(choose_device(args.device))
    events = profile_launches(rt)

    if args.peaks and os.path.isfile(args.peaks):
        with open(args.peaks) as f:
            peaks = json.load(f)
    else:
        from peak_probe import measure
        peaks = measure(rt, 128, 3)
    bw_peak = max(peaks["copy_gbs"], peaks["triad_gbs"])
    fl_peak = peaks["fma_gflops"]

    cam = Camera(FOCAL * args.width / 640, FOCAL * args.width / 640, args.width / 2, args.height / 2,
                 args.width, args.height)
    params = upload(rt, tissue_scene(args.n, args.width, args.height, 2.5))
    rng = np.random.default_rng(1)
    v_feat = cla.to_device(rt.queue, rng.standard_normal((args.height, args.width, 6)).astype(np.float32) * 1e-3)
    per = defaultdict(list)
    launches = defaultdict(int)
    for i in range(args.warmup + args.runs):
        events.clear()
        out = render(rt, params, cam, 0.5, 0.55)
        render_backward(rt, params, out, v_feat)
        rt.queue.finish()
        if i >= args.warmup:
            if i == args.warmup:
                for name, _ in events:
                    launches[name] += 1
            for k, v in kernel_ms(events).items():
                per[k].append(v)

    C = int(out.proj.features.shape[1])
    sizes = {"N": args.n, "visible": int((out.proj.radius.get() > 0).sum()), "M": out.n_isect,
             "pixels": args.width * args.height, "C": C, "tiles": int(out.tile_ranges.shape[0]),
             "sh_floats": int(np.prod(params["sh"].shape[1:])),
             "det": (not rt.caps.simt) if hasattr(rt, "caps") else not rt.is_gpu}
    tile_bits = key_bits(sizes["tiles"]) - DEPTH_BITS
    sizes["tile_passes"] = sort_passes(tile_bits, config_for_bits(rt, sizes["M"], tile_bits).radix_bits)
    sizes["depth_passes"] = launches.get("radix_scatter", 0) - sizes["tile_passes"]
    sizes["lanes_fwd"], sizes["lanes_bwd"] = lane_evaluations(out.raster, out.binned, out.proj,
                                                              args.width, args.height, C)
    rows = []
    for name, ts in per.items():
        ms = statistics.median(ts)
        by, fl = estimates(name, sizes)
        rows.append({"kernel": name, "stage": stage_of(name), "launches": launches[name], "ms": ms,
                     "bytes": by, "flops": fl,
                     "gbs": by / ms / 1e6 if by else None, "gflops": fl / ms / 1e6 if fl else None})
    order = ["project", "bin_sort", "rasterize", "rasterize_bwd", "project_bwd"]
    rows.sort(key=lambda r: (order.index(r["stage"]), -r["ms"]))
    load = " ".join(f"{v:.2f}" for v in os.getloadavg())
    head = (f"device: {rt.describe()}\nload average (1, 5, 15 min) after the runs: {load}\n"
            f"sizes: N={sizes['N']} ({sizes['visible']} visible), {args.width}x{args.height}, C={C}, "
            f"M={sizes['M']} tile pairs, sort passes: {sizes['depth_passes']} by depth over the Gaussians, "
            f"{sizes['tile_passes']} by tile over the pairs; kernel times: median of {args.runs} "
            f"runs (OpenCL event profiling) after {args.warmup}\n"
            f"peaks (benchmarks/peak_probe.py, load {peaks.get('load_before', '?')}): copy {peaks['copy_gbs']:.1f} GB/s, "
            f"triad {peaks['triad_gbs']:.1f} GB/s, FMA {fl_peak:.1f} GFLOP/s\n"
            f"estimated lane evaluations: forward {sizes['lanes_fwd']}, adjoint {sizes['lanes_bwd']}")
    lines = ["| stage | kernel | launches | ms | MB moved (est.) | GB/s | % of BW peak | MFLOP (est.) | GFLOP/s | % of FMA peak |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    stage_ms = defaultdict(float)
    for r in rows:
        stage_ms[r["stage"]] += r["ms"]
        f = lambda v, fmt: (fmt % v) if v is not None else "-"   # noqa: E731
        lines.append(f"| {r['stage']} | {r['kernel']} | {r['launches']} | {r['ms']:.2f} | "
                     f"{f(r['bytes'] and r['bytes'] / 1e6, '%.1f')} | {f(r['gbs'], '%.1f')} | "
                     f"{f(r['gbs'] and 100 * r['gbs'] / bw_peak, '%.0f%%')} | {f(r['flops'] and r['flops'] / 1e6, '%.0f')} | "
                     f"{f(r['gflops'], '%.2f')} | {f(r['gflops'] and 100 * r['gflops'] / fl_peak, '%.0f%%')} |")
    lines.append("")
    lines.append("stage totals (kernel time only): " + ", ".join(f"{k} {stage_ms[k]:.1f} ms" for k in order if k in stage_ms))
    text = head + "\n\n" + "\n".join(lines)
    print(text)
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write(text + "\n")
    if args.png:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(7.5, 5))
        ai = np.logspace(-2, 3, 200)
        ax.loglog(ai, np.minimum(fl_peak, bw_peak * ai), "k-", lw=1.5, label="measured roofs (peak_probe)")
        ax.axhline(fl_peak, color="k", lw=0.5, ls=":")
        for r in rows:
            if r["bytes"] and r["flops"]:
                x = r["flops"] / r["bytes"]
                ax.loglog(x, r["gflops"], "o", ms=4 + min(10, r["ms"] / 10))
                if r["ms"] >= 1.0:   # label the kernels that matter (marker size ~ time)
                    ax.annotate(f"{r['kernel']} {r['ms']:.1f} ms", (x, r["gflops"]), fontsize=7,
                                xytext=(5, -3 if "bwd" in r["kernel"] else 4), textcoords="offset points")
        ax.set_xlabel("arithmetic intensity (flop / byte, estimated)")
        ax.set_ylabel("achieved GFLOP/s")
        ax.set_title(f"endowave-cl kernels, {args.width}x{args.height}, {args.n} Gaussians\n"
                     f"{rt.name.split('/')[-1].strip()[:60]}, load {load.split()[0]}", fontsize=9)
        ax.grid(True, which="both", lw=0.3)
        ax.legend(fontsize=8, loc="lower right")
        fig.tight_layout()
        fig.savefig(args.png, dpi=110)
        print(f"wrote {args.png}")


if __name__ == "__main__":
    main()
