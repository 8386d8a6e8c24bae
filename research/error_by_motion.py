#!/usr/bin/env python
"""Where a trained model's error sits, by how fast the tissue moves, and how well its Gaussians
carry the motion.

1. PSNR by motion region on the test frames, beside the same regions of the neighbouring
   training frames (what the model fits) and of the baselines (endowave_cl/baselines.py).
   A pixel's region is set by the DIS flow between the test frame's two neighbouring training
   frames: slow (< 2 px), mid (2-6 px), fast (>= 6 px).  The gap between the test and training
   columns is what the model loses between frames.
2. Per-Gaussian velocity error: for the opaque Gaussians whose own time lies within half a frame
   spacing of a training frame, their projected velocity (px per frame spacing) against the DIS
   flow (per spacing) under their centre.  The composited flow can be right while the
   Gaussians of a pixel scatter around it; the scatter is what blurs renders between frames.

    python research/error_by_motion.py RUN_DIR SCENE --downscale 2 [--png regions.png]
"""
from __future__ import annotations

import argparse
import sys


EDGES = (2.0, 6.0)                      # px of DIS flow between the neighbours: slow | mid | fast
REGIONS = ("slow", "mid", "fast")
OPAQUE = 0.3                            # Gaussians above this opacity count in the velocity part


def region_psnr(sq_err_sums, counts):
    import numpy as np
    return [float(10 * np.log10(c / s)) if c and s > 0 else float("nan") for s, c in zip(sq_err_sums, counts)]


def region_chart_png(rows, fractions, title: str) -> bytes:
    """PNG bytes: grouped bars of PSNR per motion region, one bar per row of the table."""
    import io

    import matplotlib
    matplotlib.use("Agg")
    import numpy as np
    from matplotlib.figure import Figure
    fig = Figure(figsize=(7.0, 3.4), dpi=110)
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(REGIONS))
    width = 0.8 / len(rows)
    for j, (name, vals) in enumerate(rows.items()):
        ax.bar(x + (j - (len(rows) - 1) / 2) * width, vals, width, label=name)
    ax.set_xticks(x, [f"{r} ({100 * f:.0f}% of pixels)" for r, f in zip(REGIONS, fractions)])
    lo = min(min(v) for v in rows.values())
    ax.set_ylim(np.floor(lo) - 1, None)
    ax.set_ylabel("PSNR (dB), pooled over the test frames")
    ax.set_title(title, fontsize=8)
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", help="run folder (its latest checkpoint) or a checkpoint .npz")
    ap.add_argument("scene", help="the scene folder it was trained on")
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--png", help="also draw the region table as a bar chart into this PNG (atomically)")
    ap.add_argument("--title", help="the chart's title (default: the run)")
    args = ap.parse_args(argv)

    import numpy as np

    from endowave_cl import baselines as B
    from endowave_cl.checkpoint import latest_checkpoint, load_checkpoint
    from endowave_cl.data.flow import estimate_flow
    from endowave_cl.data.scene import load_scene
    from endowave_cl.errors import EndowaveError
    from endowave_cl.gaussians import covariance_4d, upload
    from endowave_cl.render import render
    from endowave_cl.runtime import get_runtime
    from endowave_cl.train.motion import motion_of

    try:
        ck = load_checkpoint(args.run if args.run.endswith(".npz") else latest_checkpoint(args.run))
        scene = load_scene(args.scene, downscale=args.downscale)
    except EndowaveError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    g = ck["gaussians"]
    rt = get_runtime()
    params = upload(rt, g)

    def rendered(k):
        f = scene.frames[k]
        return np.clip(render(rt, params, f.camera, f.time).host()["image"], 0, 1)

    names = ("model, test frames", "model, training neighbours", "neighbour mean", "DIS interpolation")
    sums = {n: np.zeros(3) for n in names}
    counts = {n: np.zeros(3) for n in names}
    for k in scene.test_indices:
        i0, i1, a = B.neighbours(scene, k)
        im0, im1 = scene.frames[i0].image, scene.frames[i1].image
        region = np.digitize(np.linalg.norm(estimate_flow(im0, im1, "dis"), axis=-1), EDGES)   # [H, W]
        gt = scene.frames[k].image
        pairs = [("model, test frames", rendered(k), gt), ("neighbour mean", B.mean_interpolation(im0, im1, a), gt),
                 ("DIS interpolation", B.dis_interpolation(im0, im1, a), gt)]
        pairs += [("model, training neighbours", rendered(i), scene.frames[i].image) for i in (i0, i1) if i != k]
        for name, pred, ref in pairs:
            se = ((pred - ref) ** 2).mean(-1)
            for r in range(3):
                sums[name][r] += se[region == r].sum()
                counts[name][r] += (region == r).sum()
    n_all = counts["model, test frames"].sum()
    print(f"{args.run}: {len(g)} Gaussians, step {ck.get('step', '?')}; {len(scene.test_indices)} test frames, "
          f"{scene.width}x{scene.height}")
    print("pixels per region (test frames): " + ", ".join(
        f"{n} {c / max(n_all, 1):.3f}" for n, c in zip(REGIONS, counts["model, test frames"])))
    print(f"{'PSNR dB':<28}" + "".join(f"{n:>8}" for n in REGIONS) + f"{'pooled':>8}")
    for name in names:
        ps = region_psnr(sums[name], counts[name])
        tot = region_psnr([sums[name].sum()], [counts[name].sum()])[0]
        print(f"{name:<28}" + "".join(f"{p:8.2f}" for p in ps) + f"{tot:8.2f}")

    if args.png:
        from endowave_cl.atomic import write_bytes_atomic
        write_bytes_atomic(args.png, region_chart_png({n: region_psnr(sums[n], counts[n]) for n in names},
                                                      counts["model, test frames"] / max(n_all, 1), args.title or args.run))

    # per-Gaussian velocity against the flow under the centre, at the training frames
    _, sigma_t, vel = motion_of(covariance_4d(g))                  # [N], [N, 3] per unit time
    opac = 1.0 / (1.0 + np.exp(-g.opacity))
    train = sorted(scene.train_indices)
    times = np.array([scene.frames[k].time for k in train])
    spacing = float(np.median(np.diff(times))) if len(times) > 1 else 1.0
    errs = []
    for a_k, b_k in zip(train[:-1], train[1:]):
        f = scene.frames[a_k]
        cam, (H, W) = f.camera, f.image.shape[:2]
        near = (np.abs(g.means[:, 3] - f.time) < 0.5 * spacing) & (opac > OPAQUE)
        if not near.any():
            continue
        flow = estimate_flow(f.image, scene.frames[b_k].image, "dis") / ((scene.frames[b_k].time - f.time) / spacing)
        view = cam.viewmat.astype(np.float64)
        pc = g.means[near, :3] @ view[:3, :3].T + view[:3, 3]       # [M, 3] camera space
        vc = vel[near] @ view[:3, :3].T
        z = pc[:, 2]
        ok = z > 0
        u = cam.fx * pc[:, 0] / np.where(ok, z, 1) + cam.cx
        v = cam.fy * pc[:, 1] / np.where(ok, z, 1) + cam.cy
        ok &= (u >= 0) & (u < W) & (v >= 0) & (v < H)
        # d(u)/dt of the projection, per frame spacing
        du = cam.fx * (vc[:, 0] * z - pc[:, 0] * vc[:, 2]) / np.where(ok, z * z, 1) * spacing
        dv = cam.fy * (vc[:, 1] * z - pc[:, 1] * vc[:, 2]) / np.where(ok, z * z, 1) * spacing
        ref = flow[v[ok].astype(int), u[ok].astype(int)]
        errs.append(np.linalg.norm(np.stack([du[ok], dv[ok]], 1) - ref, axis=1))
    if errs:
        e = np.concatenate(errs)
        print(f"per-Gaussian velocity error vs DIS under the centre ({e.size} opaque Gaussians at training "
              f"frames), px per frame spacing: median {np.median(e):.2f}, 75th {np.percentile(e, 75):.2f}, "
              f"90th {np.percentile(e, 90):.2f}")
        print(f"temporal std in frame spacings: median {np.median(sigma_t) / spacing:.2f}, "
              f"10th {np.percentile(sigma_t, 10) / spacing:.2f}, 90th {np.percentile(sigma_t, 90) / spacing:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
