"""The EndoWave training loop on the OpenCL device.

One step (``Trainer.train_step``) follows ../shared/DESIGN.md's data flow:

    render at t_k with flow to the next training frame   (project4d -> bin -> sort -> rasterize)
    losses -> one scalar and the gradient image           (RGB L1 + D-SSIM, depth, flow: torch on
                                                           the host; rational wavelet: OpenCL)
    render_backward                                       (rasterize_bwd -> project4d_bwd)
    Adam                                                  (one fused OpenCL kernel)

Parameters and Adam moments stay on the device; the host reads back the rendered channels (for
the torch losses), a scalar per gradient group (the NaN guard), and the parameters only when
densifying, checkpointing or exporting.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional

import numpy as np

from ..atomic import write_bytes_atomic
from ..errors import EndowaveError
from ..gaussians import Gaussians, download, upload
from ..render import DEPTH, FLOW, RGB, render, render_backward


class TrainingDiverged(EndowaveError):
    """A step produced a non-finite loss or gradient; it was not applied."""


@dataclass
class FrameTargets:
    """What one training frame supervises, as torch tensors (and device copies for the wavelet loss)."""
    image: "object"                    # torch [H, W, 3]
    depth: Optional["object"]          # torch [H, W] or None
    mask: Optional["object"]           # torch [H, W] (1 = tissue) or None
    flow: Optional["object"]           # torch [H, W, 2] pseudo ground-truth flow to next_index, or None
    flow_valid: Optional["object"]     # torch [H, W] consistency mask, or None
    next_time: Optional[float]         # time of the frame the flow points to
    image_dev: "object" = None         # cla [H, W, 3] for the wavelet loss
    mask_dev: "object" = None          # cla [H, W] or None


def scene_extent(g: Gaussians) -> float:
    """Radius of the initial point cloud around its centroid (the camera is static, so 3DGS's
    camera-spread extent would be 0); scales position learning rates and densification."""
    if len(g) == 0:
        return 1.0
    xyz = g.means[:, :3].astype(np.float64)
    return float(max(1e-3, np.percentile(np.linalg.norm(xyz - xyz.mean(0), axis=1), 95) * 1.1))


class Trainer:
    def __init__(self, scene, cfg, run_dir, rt, log: Callable[[str], None] = print, resume: bool = True):
        from ..ops.adam import DeviceAdam
        from .checkpoint import latest_checkpoint, load_checkpoint

        self.scene, self.cfg, self.rt, self.log = scene, cfg, rt, log
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        # the run folder describes itself: render / eval / export read this
        write_bytes_atomic(self.run_dir / "config.json", json.dumps(
            {"scene": str(Path(scene.path).resolve()), **cfg.to_dict()}, indent=1).encode())
        self.rng = np.random.default_rng(cfg.seed)
        self.step = 0
        self.history: List[Dict[str, float]] = []

        ckpt_path = latest_checkpoint(self.run_dir) if resume else None
        if ckpt_path is not None:
            ck = load_checkpoint(ckpt_path)
            g = ck["gaussians"]
            self.step = int(ck["step"])
            self.extent = float(ck["extra"].get("extent", scene_extent(g)))
            self.log(f"resuming from {ckpt_path} at step {self.step} ({len(g)} Gaussians)")
        else:
            from .init import init_gaussians
            g = init_gaussians(scene.frames, scene.train_indices, scene.near, scene.far,
                               max_points=cfg.init_points, seed=cfg.seed, time_scale=cfg.init_time_scale)
            self.extent = scene_extent(g)
            ck = None
        self.params = upload(rt, g)
        self.adam = DeviceAdam(rt, self.params, self.group_lrs(self.step))
        if ck is not None and ck.get("adam_state"):
            self.adam.load_state_dict(ck["adam_state"])
        self._reset_stats()
        self.targets = self._prepare_targets()

    # ------------------------------------------------------------------ setup
    def group_lrs(self, step: int) -> Dict[str, float]:
        from ..ops.adam import position_lr
        c = self.cfg
        steps = c.lr_position_steps or c.iterations
        return {
            "means": position_lr(step, steps, c.lr_position_init, c.lr_position_final, self.extent),
            "means_t": c.lr_time,
            "scales": c.lr_scales, "quat_l": c.lr_rotation, "quat_r": c.lr_rotation,
            "opacity": c.lr_opacity, "sh": c.lr_features, "sh_rest": c.lr_features / c.lr_features_rest_divisor,
            "phase": c.lr_phase,
        }

    def _reset_stats(self):
        import pyopencl.array as cla
        n = len(self.params["means"])
        q = self.rt.queue
        self.stats = {"grad_accum": cla.zeros(q, (n,), np.float32), "count": cla.zeros(q, (n,), np.int32),
                      "max_radius": cla.zeros(q, (n,), np.float32)}

    def _prepare_targets(self) -> Dict[int, FrameTargets]:
        import pyopencl.array as cla
        import torch
        sc, c = self.scene, self.cfg
        flows = {}
        if c.use_flow:
            from ..data.flow import flow_for_scene
            flows = dict(flow_for_scene(sc, method=getattr(c, "flow_method", "dis"), progress=False))
        out = {}
        order = list(sc.train_indices)
        for j, k in enumerate(order):
            f = sc.frames[k]
            pair = flows.get(k)
            mask = None if f.mask is None else torch.from_numpy(np.ascontiguousarray(f.mask, np.float32))
            depth = None
            if c.use_depth and f.depth is not None:
                depth = torch.from_numpy(np.ascontiguousarray(f.depth, np.float32))
            out[k] = FrameTargets(
                image=torch.from_numpy(np.ascontiguousarray(f.image, np.float32)), depth=depth, mask=mask,
                flow=None if pair is None else torch.from_numpy(pair.flow),
                flow_valid=None if pair is None else torch.from_numpy(pair.valid),
                next_time=None if pair is None else float(sc.frames[pair.dst].time),
                image_dev=cla.to_device(self.rt.queue, np.ascontiguousarray(f.image, np.float32)) if c.use_wavelet else None,
                mask_dev=(cla.to_device(self.rt.queue, np.ascontiguousarray(f.mask, np.float32))
                          if (c.use_wavelet and f.mask is not None) else None))
        return out

    # ------------------------------------------------------------------ one step
    def train_step(self, k: int) -> Dict[str, float]:
        """One optimisation step on training frame k."""
        frame, tgt = self.scene.frames[k], self.targets[k]
        out = render(self.rt, self.params, frame.camera, frame.time, tgt.next_time)        # forward
        total, parts, v_features = self.losses_and_gradient(out, tgt)                    # losses
        grads = render_backward(self.rt, self.params, out, v_features, densify_stats=self.stats,   # adjoints
                                deterministic=True if self.cfg.deterministic else None)
        self._check_finite(total, grads, k)
        self.adam.step({name[2:]: v for name, v in grads.items()}, self.group_lrs(self.step))  # Adam (v_means -> means)
        self.step += 1
        return parts

    def losses_and_gradient(self, out, tgt: FrameTargets):
        """Total loss, its parts, and the gradient image v_features [H, W, C] on the device."""
        import pyopencl.array as cla
        import torch

        from .losses import image_losses
        c = self.cfg
        feats = torch.from_numpy(out.features.get()).requires_grad_(True)   # [H, W, C]
        pred = {"image": feats[..., RGB], "depth": feats[..., DEPTH], "flow": feats[..., FLOW]}
        target = {"image": tgt.image, "mask": tgt.mask, "depth": tgt.depth,
                  "flow": tgt.flow if c.use_flow else None, "flow_valid": tgt.flow_valid if c.use_flow else None}
        total, parts = image_losses(pred, target, c)
        total.backward()
        v = feats.grad.numpy()
        total_value = float(total.detach())
        if c.use_wavelet and c.lambda_wavelet > 0:
            from ..wavelet.loss import wavelet_loss_and_grad
            rgb = cla.to_device(self.rt.queue, np.ascontiguousarray(feats.detach().numpy()[..., RGB]))
            wl, v_rgb = wavelet_loss_and_grad(self.rt, rgb, tgt.image_dev, tgt.mask_dev, self.wavelet_config)
            v[..., RGB] += c.lambda_wavelet * v_rgb.get()
            parts["wavelet"] = wl
            total_value += c.lambda_wavelet * wl
        parts["total"] = total_value
        with torch.no_grad():  # training PSNR on the supervised (tissue) pixels
            sq = (feats[..., RGB] - tgt.image) ** 2
            mse = float(sq.mean() if tgt.mask is None else (sq * tgt.mask[..., None]).sum() / (3 * tgt.mask.sum()).clamp(min=1))
        parts["psnr"] = 10 * math.log10(1.0 / max(mse, 1e-12))
        return total_value, parts, cla.to_device(self.rt.queue, np.ascontiguousarray(v, np.float32))

    @property
    def wavelet_config(self):
        from ..wavelet.loss import WaveletConfig
        if not hasattr(self, "_wcfg"):
            self._wcfg = WaveletConfig()
        return self._wcfg

    def _check_finite(self, total: float, grads, k: int):
        from ..ops.util import any_nonfinite
        bad = [] if math.isfinite(total) else ["loss"]
        if any_nonfinite(self.rt, grads.values()):
            bad.append("gradients")
        if bad:
            raise TrainingDiverged(f"step {self.step} (frame {k}): non-finite {', '.join(bad)}; the step was not "
                                   f"applied. Last checkpoint: {self.run_dir}. Try lower learning rates.")

    # ------------------------------------------------------------------ density control
    def densify(self):
        """3DGS density control in 4D on the host: clone, split (children sampled in space-time), prune."""
        from .densify import densify_and_prune, moment_source_index
        info: Dict[str, object] = {}
        new_g, source = densify_and_prune(
            download(self.params), self.stats["grad_accum"].get(), self.stats["count"].get(),
            self.stats["max_radius"].get(), self.cfg, self.extent, self.rng,
            prune_big=self.step > self.cfg.opacity_reset_every, stats=info)
        self.set_gaussians(new_g, moment_source_index(source, info["is_new"]))  # new rows: zero moments

    def set_gaussians(self, g: Gaussians, source_index: np.ndarray):
        """Replace the parameters; row i's Adam moments come from old row source_index[i] (< 0: zero)."""
        self.params = upload(self.rt, g)
        self.adam.remap(self.params, source_index)
        self._reset_stats()

    def reset_opacity(self):
        from .densify import reset_opacity
        g = reset_opacity(download(self.params), self.cfg.opacity_reset_value)
        self.set_gaussians(g, np.arange(len(g)))
        self.adam.reset_moments("opacity")

    # ------------------------------------------------------------------ evaluation, checkpoints
    def evaluate(self) -> Dict[str, float]:
        """Test-frame PSNR (both forms) and SSIM; LPIPS and FPS are left to `endowave-cl eval`."""
        from ..evaluation import evaluate_run
        return evaluate_run(self.rt, self.params, self.scene, fps_runs=0, with_lpips=False)

    def save(self):
        from .checkpoint import save_checkpoint
        path = self.run_dir / f"checkpoint_{self.step:07d}.npz"
        save_checkpoint(path, download(self.params), self.adam.state_dict(), self.step, self.cfg.to_dict(),
                        {"extent": self.extent, "scene": str(self.scene.path)})
        # keep the two newest checkpoints
        for old in sorted(self.run_dir.glob("checkpoint_*.npz"))[:-2]:
            old.unlink()
        return path

    # ------------------------------------------------------------------ the loop
    def train(self, progress: bool = True) -> Dict[str, float]:
        from tqdm import tqdm
        c = self.cfg
        order = list(self.scene.train_indices)
        bar = tqdm(total=c.iterations, initial=self.step, disable=not progress, dynamic_ncols=True,
                   desc="train", unit="it")
        t_start = time.perf_counter()
        ema = None
        while self.step < c.iterations:
            k = order[int(self.rng.integers(len(order)))]
            parts = self.train_step(k)
            ema = parts if ema is None else {key: 0.9 * ema.get(key, v) + 0.1 * v for key, v in parts.items()}
            s = self.step
            if c.densify_from <= s <= c.densify_until and s % c.densify_every == 0:
                self.densify()
            if s > 0 and s % c.opacity_reset_every == 0 and s <= c.densify_until:
                self.reset_opacity()
            if s % c.log_every == 0 or s == c.iterations:
                bar.set_postfix(loss=f"{ema['total']:.4f}", psnr=f"{ema['psnr']:.2f}", N=len(self.params["means"]))
                self.history.append({"step": s, **{k2: float(v) for k2, v in ema.items()},
                                     "gaussians": len(self.params["means"])})
            if c.eval_every and s % c.eval_every == 0 and s < c.iterations:
                m = self.evaluate()
                bar.write(f"step {s}: test PSNR {m['psnr']:.2f} dB (masked {m['psnr_masked']:.2f}), "
                          f"SSIM {m['ssim']:.3f}, {len(self.params['means'])} Gaussians")
            if c.checkpoint_every and s % c.checkpoint_every == 0:
                self.save()
            bar.update(1)
        bar.close()
        seconds = time.perf_counter() - t_start
        self.save()
        metrics = self.evaluate()
        metrics.update({"step": self.step, "gaussians": len(self.params["means"]), "train_seconds": seconds})
        write_bytes_atomic(self.run_dir / "train_log.json",
                           json.dumps({"final": metrics, "history": self.history}, indent=1).encode())
        return metrics
