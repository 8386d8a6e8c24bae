"""Can the two neighbouring frames alone say which warp to trust?  A per-scene learned chooser.

Finding 11 (research/QUALITY.md) found that, per 7x7 patch, the best of the candidate warps of several
flow estimators would interpolate a test frame 2.4 dB better than the DIS interpolation, and that
rules built from the two frames (the warps' agreement, forward-backward consistency) do not find
that choice.  This tool asks whether a small convolutional network, trained on the scene's own
training frames, does.

For every frame k whose neighbours k - 1 and k + 1 are both training frames, the candidates are,
for each estimator of --methods, the two one-sided warps W0 = I_{k-1}(p - F_01 / 2) and
W1 = I_{k+1}(p - F_10 / 2) (bicubic) and their blend.  The network sees the warps and their
per-estimator disagreement |W0 - W1| and puts a softmax over the candidates at every pixel; its
output is the weighted sum.  It is trained (L1, random crops) on the triplets (k - 1, k, k + 1) of
training frames only, and scored on the test frames, whose neighbours are training frames at the
same spacing, beside the DIS interpolation and the plain mean of the candidates.

    python research/interp_chooser.py ../shared/data/endonerf/pulling_soft_tissues --downscale 2
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--methods", default="dis,dis_fine,farneback", help="comma-separated data/flow.py METHODS")
    ap.add_argument("--iterations", type=int, default=600, help="Adam steps of the chooser")
    ap.add_argument("--crop", type=int, default=96, help="side of the random training crops (px)")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--width", type=int, default=24, help="channels of the network's hidden layers")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import torch
    import torch.nn as nn

    from endowave_cl.baselines import sample_displaced
    from endowave_cl.data.flow import METHODS, estimate_flow
    from endowave_cl.data.scene import load_scene
    from endowave_cl.errors import EndowaveError
    from endowave_cl.metrics import psnr
    from quality_run import _machine

    methods = a.methods.split(",")
    if any(m not in METHODS for m in methods):
        ap.error(f"--methods from {', '.join(METHODS)}")
    try:
        sc = load_scene(a.scene, downscale=a.downscale)
    except EndowaveError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    torch.manual_seed(a.seed)
    rng = np.random.default_rng(a.seed)
    n, test = len(sc.frames), set(sc.test_indices)
    train_k = [k for k in range(1, n - 1) if not {k - 1, k, k + 1} & test]
    test_k = [k for k in sorted(test) if 0 < k < n - 1]
    print(f"{a.scene} {sc.width}x{sc.height}; {_machine()}; torch threads {torch.get_num_threads()}")
    print(f"{len(train_k)} training triplets, {len(test_k)} test frames; estimators {', '.join(methods)}")
    t0 = time.perf_counter()

    def candidates(k):                      # [M, 2, 3, H, W]: each estimator's W0, W1 at s = 1/2
        im0, im1 = sc.frames[k - 1].image, sc.frames[k + 1].image
        out = []
        for m in methods:
            f01, f10 = estimate_flow(im0, im1, m), estimate_flow(im1, im0, m)
            out.append([sample_displaced(im0, -0.5 * f01, "cubic"), sample_displaced(im1, -0.5 * f10, "cubic")])
        return torch.from_numpy(np.asarray(out, np.float32)).permute(0, 1, 4, 2, 3).contiguous()

    cand = {k: candidates(k) for k in train_k + test_k}
    gt = {k: torch.from_numpy(np.ascontiguousarray(sc.frames[k].image, np.float32)).permute(2, 0, 1) for k in cand}
    print(f"candidates: {time.perf_counter() - t0:.1f} s")

    def features(c):                        # [B, M, 2, 3, H, W] -> [B, 7M, H, W]
        diff = (c[:, :, 0] - c[:, :, 1]).abs().sum(2)                               # [B, M, H, W]
        return torch.cat([c.flatten(1, 3), diff], 1)

    def choose(logits, c):                  # softmax over the 3M candidates (W0, W1, blend per estimator)
        allc = torch.cat([c[:, :, 0], c[:, :, 1], 0.5 * (c[:, :, 0] + c[:, :, 1])], 1)   # [B, 3M, 3, H, W]
        return (torch.softmax(logits, 1).unsqueeze(2) * allc).sum(1)

    m3, w = 3 * len(methods), a.width
    net = nn.Sequential(nn.Conv2d(7 * len(methods), w, 3, padding=1), nn.ReLU(),
                        nn.Conv2d(w, w, 3, padding=2, dilation=2), nn.ReLU(),
                        nn.Conv2d(w, w, 3, padding=4, dilation=4), nn.ReLU(),
                        nn.Conv2d(w, w, 3, padding=1), nn.ReLU(), nn.Conv2d(w, m3, 1))
    nn.init.zeros_(net[-1].weight)          # start as the plain mean of the candidates
    nn.init.zeros_(net[-1].bias)
    opt = torch.optim.Adam(net.parameters(), 2e-3)
    h, wd, cs = sc.height, sc.width, a.crop
    for it in range(a.iterations):
        cb, gb = [], []
        for k in rng.choice(train_k, a.batch):
            y, x = int(rng.integers(0, h - cs + 1)), int(rng.integers(0, wd - cs + 1))
            cb.append(cand[k][..., y:y + cs, x:x + cs])
            gb.append(gt[k][:, y:y + cs, x:x + cs])
        cb, gb = torch.stack(cb), torch.stack(gb)
        loss = (choose(net(features(cb)), cb) - gb).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if it % 100 == 0 or it == a.iterations - 1:
            print(f"  step {it}: L1 {loss.item():.5f} ({time.perf_counter() - t0:.0f} s)", flush=True)

    def scores(ks):
        rows = {"DIS interpolation (bicubic)": [], "mean of the candidates": [], "learned chooser": []}
        with torch.no_grad():
            for k in ks:
                c, g = cand[k][None], gt[k].permute(1, 2, 0).numpy()
                img = lambda t: t[0].permute(1, 2, 0).clamp(0, 1).numpy()     # noqa: E731
                rows["DIS interpolation (bicubic)"].append(psnr(img(0.5 * (c[:, 0, 0] + c[:, 0, 1])), g))
                rows["mean of the candidates"].append(psnr(img(c.mean((1, 2))), g))
                rows["learned chooser"].append(psnr(img(choose(net(features(c)), c)), g))
        return rows

    tr, te = scores(train_k), scores(test_k)
    print(f"\n| interpolator | training triplets ({len(train_k)}) | test frames ({len(test_k)}) |\n|---|---|---|")
    for name in tr:
        print(f"| {name} | {np.mean(tr[name]):.2f} | {np.mean(te[name]):.2f} |")
    print("\nper test frame (DIS / mean / chooser): " + ", ".join(
        f"{k}: {te['DIS interpolation (bicubic)'][i]:.2f} / {te['mean of the candidates'][i]:.2f} / "
        f"{te['learned chooser'][i]:.2f}" for i, k in enumerate(test_k)))
    print(f"{time.perf_counter() - t0:.0f} s in all")
    return 0


if __name__ == "__main__":
    sys.exit(main())
