"""The EndoWave training loop on the OpenCL device.

One step (``Trainer.train_step``) follows ../shared/DESIGN.md's data flow:

    render at t_k with flow to the next training frame   (project4d -> bin -> sort -> rasterize)
    losses -> one scalar and the gradient image           (RGB L1 + D-SSIM, depth, flow, rational
                                                           wavelet: OpenCL, train/device_losses.py)
    render_backward                                       (rasterize_bwd -> project4d_bwd)
    Adam                                                  (one fused OpenCL kernel)

Parameters, Adam moments, the rendered images and every frame's targets stay on the device; the
host reads back a few loss sums per step, a flag per gradient group (the NaN guard), and the
parameters only when densifying, checkpointing or exporting.
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
from ..render import DEPTH, FLOW, render, render_backward


class TrainingDiverged(EndowaveError):
    """A step produced a non-finite loss or gradient; it was not applied."""


@dataclass
class FrameTargets:
    """What one training frame supervises, on the device, and the time its flow points to."""
    dev: "object"                      # device_losses.DeviceTargets
    next_time: Optional[float]         # time of the frame the flow points to (None: no flow)


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
        from .device_losses import prepare_targets
        sc, c = self.scene, self.cfg
        flows = {}
        if c.use_flow:
            from ..data.flow import flow_for_scene
            flows = dict(flow_for_scene(sc, method=getattr(c, "flow_method", "dis"), progress=False))
        out = {}
        for k in sc.train_indices:
            f = sc.frames[k]
            pair = flows.get(k)
            out[k] = FrameTargets(
                prepare_targets(self.rt, f.image, f.mask, f.depth if c.use_depth else None,
                                None if pair is None else pair.flow, None if pair is None else pair.valid),
                next_time=None if pair is None else float(sc.frames[pair.dst].time))
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
        """Total loss, its parts (and the training PSNR), and the gradient image v_features
        [H, W, C], all computed on the device (train/device_losses.py)."""
        from .device_losses import image_losses_and_grad
        return image_losses_and_grad(self.rt, out.features, tgt.dev, self.cfg, {"depth": DEPTH, "flow": FLOW.start},
                                     self.wavelet_config)

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
        from ..progress import progress as progress_bar
        c = self.cfg
        order = list(self.scene.train_indices)
        bar = progress_bar(total=c.iterations, initial=self.step, disable=not progress, dynamic_ncols=True,
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
