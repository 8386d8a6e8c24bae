#!/usr/bin/env python
"""Choose q and the band weights of the wavelet loss by a small fitting experiment.

A synthetic endoscopy-like image (endowave_cl/wavelet/synthetic.py: smooth tissue, vessels,
texture, small saturated specular highlights) is fitted by a capacity-limited 2D "splatting"
model: N anisotropic 2D Gaussians with colours, summed (no ordering), optimised with Adam for a
fixed number of steps, once with L1 alone and once with L1 + the rational-wavelet loss
(the pure-torch implementation, which the tests tie to the OpenCL kernels) for each q and weight
set.  Reported per configuration, mean over seeds: PSNR of the whole image, PSNR inside the
highlights (mask dilated by 2 px), mean absolute error inside the highlights, and SSIM.

    python research/tune_wavelet.py [--steps 200 --gaussians 120 --seeds 2 --size 64x80]
"""
from __future__ import annotations

import argparse
import itertools
import time

import numpy as np


def render(params, H, W, yy, xx):
    """Sum of anisotropic 2D Gaussians: [H, W, 3]."""
    mu, log_s, theta, col = params
    s = log_s.exp()                                                  # [N, 2]
    c, sn = theta.cos(), theta.sin()
    dx = xx[None] - mu[:, 0, None]                                   # [N, HW]
    dy = yy[None] - mu[:, 1, None]
    u = (c[:, None] * dx + sn[:, None] * dy) / s[:, 0, None]
    v = (-sn[:, None] * dx + c[:, None] * dy) / s[:, 1, None]
    g = (-0.5 * (u * u + v * v)).exp()                               # [N, HW]
    return (g.t() @ col).reshape(H, W, 3)


def fit(target, steps, n_gauss, seed, wcfg, wscale):
    import torch
    from endowave_cl.reference.wavelet import wavelet_loss_ref
    H, W, _ = target.shape
    g = torch.Generator().manual_seed(seed)
    tt = torch.tensor(target)
    yy, xx = torch.meshgrid(torch.arange(H, dtype=torch.float32) + 0.5,
                            torch.arange(W, dtype=torch.float32) + 0.5, indexing="ij")
    yy, xx = yy.reshape(-1), xx.reshape(-1)
    mu = torch.rand(n_gauss, 2, generator=g) * torch.tensor([W, H], dtype=torch.float32)
    log_s = torch.full((n_gauss, 2), float(np.log(0.6 * np.sqrt(H * W / n_gauss))))
    theta = torch.rand(n_gauss, generator=g) * np.pi
    iy = mu[:, 1].long().clamp(0, H - 1)
    ix = mu[:, 0].long().clamp(0, W - 1)
    col = tt[iy, ix] * 0.5
    params = [p.clone().requires_grad_(True) for p in (mu, log_s, theta, col)]
    opt = torch.optim.Adam([{"params": [params[0]], "lr": 0.3}, {"params": [params[1]], "lr": 0.02},
                            {"params": [params[2]], "lr": 0.02}, {"params": [params[3]], "lr": 0.01}])
    for _ in range(steps):
        opt.zero_grad()
        img = render(params, H, W, yy, xx)
        loss = (img - tt).abs().mean()
        if wcfg is not None:
            loss = loss + wscale * wavelet_loss_ref(img, tt, None, wcfg)
        loss.backward()
        opt.step()
    with torch.no_grad():
        return render(params, H, W, yy, xx).numpy()


def metrics(pred, target, hmask):
    from scipy.ndimage import binary_dilation
    from skimage.metrics import structural_similarity
    pred = np.clip(pred, 0, 1)
    mse = np.mean((pred - target) ** 2)
    hm = binary_dilation(hmask, iterations=2)
    hmse = np.mean((pred[hm] - target[hm]) ** 2)
    return {"psnr": 10 * np.log10(1 / mse), "hl_psnr": 10 * np.log10(1 / hmse),
            "hl_mae": float(np.mean(np.abs(pred[hm] - target[hm]))),
            "ssim": float(structural_similarity(pred, target, channel_axis=2, data_range=1.0))}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--gaussians", type=int, default=120)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--size", default="64x80", help="HxW")
    ap.add_argument("--qs", default="1,2,3,4")
    ap.add_argument("--weights", default="1:1:1:1,1:2:2:2,0:1:1:1,2:1:1:1",
                    help="comma-separated LL:LH:HL:HH weight sets")
    ap.add_argument("--scales", default="4", help="overall multipliers of each weight set")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest on a busy 2-core box)")
    args = ap.parse_args(argv)
    import torch
    torch.set_num_threads(args.threads)
    from endowave_cl.wavelet.loss import WaveletConfig
    from endowave_cl.wavelet.synthetic import synthetic_endoscopy_image
    H, W = (int(v) for v in args.size.lower().split("x"))
    qs = [int(v) for v in args.qs.split(",")]
    wsets = [tuple(float(x) for x in w.split(":")) for w in args.weights.split(",")]
    scales = [float(s) for s in args.scales.split(",")]
    configs = [("L1 only", None, 0.0)]
    for q, w, s in itertools.product(qs, wsets, scales):
        configs.append((f"q={q} w={':'.join(f'{x:g}' for x in w)} x{s:g}", WaveletConfig(q=q, weights=w), s))
    targets = [synthetic_endoscopy_image(H, W, seed=100 + k, n_highlights=max(4, H * W // 1000))
               for k in range(args.seeds)]
    print(f"fit {H}x{W}, {args.gaussians} Gaussians, {args.steps} Adam steps, {args.seeds} seeds; "
          f"loss = L1 + scale * wavelet(q, weights)")
    print(f"{'config':28s} {'PSNR':>7s} {'hl PSNR':>8s} {'hl MAE':>7s} {'SSIM':>6s} {'time':>6s}")
    results = []
    for name, cfg, s in configs:
        t0 = time.perf_counter()
        ms = [metrics(fit(tg, args.steps, args.gaussians, k, cfg, s), tg, hm) for k, (tg, hm) in enumerate(targets)]
        avg = {k: float(np.mean([m[k] for m in ms])) for k in ms[0]}
        results.append((name, avg))
        print(f"{name:28s} {avg['psnr']:7.2f} {avg['hl_psnr']:8.2f} {avg['hl_mae']:7.4f} {avg['ssim']:6.4f} "
              f"{time.perf_counter() - t0:5.1f}s", flush=True)
    best = max(results[1:], key=lambda r: r[1]["psnr"] + r[1]["hl_psnr"])
    print(f"best by PSNR + highlight PSNR: {best[0]}  vs L1 only: PSNR {results[0][1]['psnr']:.2f}, "
          f"hl PSNR {results[0][1]['hl_psnr']:.2f}")


if __name__ == "__main__":
    main()
