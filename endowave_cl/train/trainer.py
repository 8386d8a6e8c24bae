"""The EndoWave training loop on the OpenCL device.

One step (``Trainer.train_step``) follows ../shared/DESIGN.md's data flow:

    render at t_k with flow to the next training frame   (select -> project4d -> bin -> sort -> rasterize)
    losses -> one scalar and the gradient image           (RGB L1 + D-SSIM, depth, flow, rational
                                                           wavelet: OpenCL, train/device_losses.py)
    render_backward                                       (rasterize_bwd -> project4d_bwd)
    Adam                                                  (one fused OpenCL kernel)

A fraction ``between_prob`` of the steps (``Trainer.train_step_between``) runs the same step at a
random time between two training frames, against the frame their flow predicts there
(train/between.py).

Parameters, Adam moments, the rendered images and every frame's targets stay on the device; per
step the host reads one small buffer of scalars (the loss sums, the gradients' NaN / Inf flag and
the step gate), and the parameters only when densifying, checkpointing or exporting.

In the loop (``Trainer.train``) that read does not block: a step is enqueued whole, gated on the
device (ops/util.py step_gate: Adam and the densification statistics leave everything as it was
where its gradients are not finite or its live rows or pairs overflowed their buffers), and its
scalars are read once the next step is enqueued.  A step found skipped there is done again from
the same draws, waiting for its outcome, and the step enqueued behind it (skipped with it: the gate
is sticky) is drawn again, so the updates, and their bits, are those of a loop that waits at every
step (``ENDOWAVE_BLOCKING_STEPS=1`` runs that loop).  Steps after which the host needs the outcome
(a log line, density control, an opacity reset, an evaluation, a checkpoint, the time budget's
first plan, the last step) wait for it.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional

import numpy as np
import pyopencl.array as cla

from .. import env
from ..data.flow import estimation_size, flow_for_scene
from ..evaluation import evaluate_run
from ..gaussians import Gaussians, covariance_4d, download, upload
from ..host_memory import keep_freed_memory
from ..ops.adam import DeviceAdam, anneal_factor, opacity_reset, position_lr
from ..ops.select import select_enabled
from ..ops.util import GATE_PAIRS, GATE_ROWS, GATE_SUPERVISED, PendingRead, nonfinite_flag, read_back, step_gate
from ..progress import hold_rate, progress as progress_bar, restart_rate
from ..render import DEPTH, FLOW, accumulate_stats, render, render_backward
from . import curves
from .average import ParameterAverage, average_start
from .between import BetweenSampler
from .between_device import motion_on_device
from .budget import MIN_TIMED_STEPS, RATE_WINDOW, WARMUP_STEPS, BudgetPlan
from .config import between_flow_methods
from .curves import TensorBoard
from .densify import densify_and_prune, logit, moment_source_index, temporal_row_order
from .device_losses import image_losses_enqueue, prepare_targets
from .guard import TrainingDiverged  # noqa: F401  (a non-finite step or a diverged run)
from .init import init_gaussians
from .motion import temporal_coverage
from .run_folder import RunSession


# $ENDOWAVE_BLOCKING_STEPS=1: the loop waits for every step's outcome before the next (the
# reference for the deferred read, with the same results; benchmarks compare the two)
ENV_BLOCKING_STEPS = "ENDOWAVE_BLOCKING_STEPS"


def deferred_steps() -> bool:
    """Whether Trainer.train reads each step's outcome after the next step is enqueued."""
    return not env.flag(ENV_BLOCKING_STEPS)


@dataclass
class HostState:
    """What the host holds that a step changes, taken before it: a skipped step is done again
    from here (Trainer._rewind)."""
    rng: dict                          # the generator's bit state (the step's draws)
    step: int
    adam_steps: int                    # DeviceAdam.step_count (the bias corrections)
    motion: Optional[dict]             # the in-between sampler's kept model motion


@dataclass
class PendingStep:
    """A step enqueued on the device, its outcome not read yet (Trainer._step_enqueued)."""
    read: PendingRead                  # the loss sums, the gradients' NaN / Inf flag, the gate
    finish: Callable                   # host sums -> (total, parts): device_losses.PendingLosses
    out: "object"                      # its render (the live-row and pair counts)
    what: str
    step: int                          # the step count once it is applied


class StepSkipped(Exception):
    """A deferred step's gate came back set for a reason that a step done again clears."""


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


def late_factor(cfg, step: int, final: float) -> float:
    """The late schedule's factor of the in-between chance: 1 until cfg.densify_until, then
    falling linearly to ``final`` at cfg.iterations."""
    if step <= cfg.densify_until or cfg.iterations <= cfg.densify_until:
        return 1.0
    u = min((step - cfg.densify_until) / float(cfg.iterations - cfg.densify_until), 1.0)
    return 1.0 - u * (1.0 - final)


ETA_WARMUP_STEPS = 5   # steps of a session before the progress rate is measured (builds, caches)


class Trainer:
    def __init__(self, scene, cfg, run_dir, rt, log: Callable[[str], None] = print, resume: bool = True,
                 progress: bool = False):
        keep_freed_memory()      # the steps' large host temporaries reuse heap memory (host_memory.py)
        self.scene, self.cfg, self.rt, self.log = scene, cfg, rt, log
        self._flow_progress = progress    # a progress bar while flows not in the cache are computed
        self.t_created = time.perf_counter()   # a time budget (cfg.minutes) counts from here
        self._build0 = getattr(rt, "build_seconds", 0.0)   # kernel builds are reported apart (runtime.py)
        self._auto_cap = cfg.max_gaussians <= 0           # raised for short lives once the model exists
        self.auto_iterations = cfg.iterations <= 0        # visits per training frame (config.py)
        # the resolved config (TrainConfig is frozen: each step gives a new one; the caller's is unchanged)
        self.cfg = cfg = (cfg.resolve_iterations(len(scene.train_indices))
                          .resolve_density(scene.width, scene.height)   # per-pixel init_points, max_gaussians
                          .resolve_sh_degree(scene.one_viewpoint()))    # sh_degree -1: 1 for a fixed camera, else 3
        self.run_dir = Path(run_dir)
        # creates and locks the run folder; config.json is written by run.start once the model is ready
        self._run = RunSession(self.run_dir, log, resume)
        try:
            self._init_model(scene, cfg, rt, resume)
        except BaseException:
            self._run.abort()
            raise

    def _init_model(self, scene, cfg, rt, resume):
        self.rng = np.random.default_rng(cfg.seed)
        self.step = 0
        self._defer = False                       # train() reads each step's outcome one step late
        self.redone_steps = 0                     # steps train() found skipped on the device and did again
        self.density_counts = {"cloned": 0, "split": 0, "pruned": 0, "replaced": 0}   # over the run
        self._skip = cla.zeros(rt.queue, (1,), np.int32)   # the step gate (ops/util.py step_gate)
        self.history: List[Dict[str, float]] = []
        self._average: Optional[ParameterAverage] = None   # the late steps' mean (cfg.average_last)

        self.flows = self._load_flows()
        ckpt_path, ck = self._run.resume_point(scene)   # newest readable checkpoint of this scene
        if ck is not None:
            g = ck["gaussians"]
            # the run's own scene units (1.0: a run from before the loader measured them)
            scene.set_world_scale(float(ck["extra"].get("world_scale", 1.0)))
            self.step = int(ck["step"])
            self.extent = float(ck["extra"].get("extent", scene_extent(g)))
            self.cfg = self.cfg.replace(sh_degree=g.sh_degree)   # the model's layout, whatever was resolved
            if self._auto_cap:                   # the cap the run started with
                self.cfg = self.cfg.replace(max_gaussians=int(ck["config"].get("max_gaussians", self.cfg.max_gaussians)))
            self.log(f"resuming from {ckpt_path} at step {self.step} ({len(g)} Gaussians)")
        else:
            g = init_gaussians(scene.frames, scene.train_indices, scene.near, scene.far,
                               max_points=cfg.init_points, seed=cfg.seed, sh_degree=cfg.sh_degree,
                               nt=cfg.temporal_freqs, time_scale=cfg.init_time_scale,
                               flows=self.flows if cfg.init_velocity else None)
            self.extent = scene_extent(g)
            if self._auto_cap and len(g):
                sigma_t = np.sqrt(np.maximum(covariance_4d(g)[:, 3, 3], 0.0))
                self.cfg = self.cfg.resolve_cap_for_lifetimes(scene.width, scene.height,
                                                              float(temporal_coverage(g.means[:, 3], sigma_t).mean()))
            ck = None
        self.params = upload(rt, g)
        self.adam = DeviceAdam(rt, self.params, self.group_lrs(self.step))
        if ck is not None and ck.get("adam_state"):
            self.adam.load_state_dict(ck["adam_state"])
        self._reset_stats()
        self.targets = self._prepare_targets()
        self._between = BetweenSampler.from_config(rt, scene, self.cfg, self.flows if cfg.between_prob > 0 else {},
                                                   self._load_between_flows())
        self._run.start(self, ck)    # restart: retire the earlier run; resume: sampling state; config.json

    # ------------------------------------------------------------------ setup
    def group_lrs(self, step: int) -> Dict[str, float]:
        c = self.cfg
        steps = c.lr_position_steps or c.iterations
        a = anneal_factor(step, c.densify_until, c.iterations, c.lr_anneal_final)
        return {
            "means": position_lr(step, steps, c.lr_position_init, c.lr_position_final, self.extent),
            "means_t": a * c.lr_time,
            "scales": a * c.lr_scales, "scales_t": a * c.lr_scales_t, "quat_l": a * c.lr_rotation, "quat_r": a * c.lr_rotation,
            "opacity": a * c.lr_opacity, "sh": a * c.lr_features,
            "sh_rest": a * c.lr_features / c.lr_features_rest_divisor, "phase": a * c.lr_phase,
        }

    def between_prob(self, step: int) -> float:
        """The chance that this step is an in-between one: between_prob until densify_until, then
        falling linearly to between_prob x between_anneal_final at the last step."""
        return self.cfg.between_prob * late_factor(self.cfg, step, self.cfg.between_anneal_final)

    def _reset_stats(self):
        n = len(self.params["means"])
        q = self.rt.queue
        self.stats = {"grad_accum": cla.zeros(q, (n,), np.float32), "count": cla.zeros(q, (n,), np.int32),
                      "max_radius": cla.zeros(q, (n,), np.float32)}

    def _load_flows(self) -> Dict[int, object]:
        """Pseudo ground-truth flow of the training pairs, {k: FlowPair} (cached on disk), when the
        flow loss or the moving initialisation needs it."""
        c = self.cfg
        if not (c.use_flow or c.init_velocity or c.between_prob > 0):
            return {}
        flows = flow_for_scene(self.scene, method=c.flow_method, progress=self._flow_progress,
                               max_pixels=c.flow_max_pixels)
        work = estimation_size(self.scene.width, self.scene.height, c.flow_max_pixels)
        if getattr(flows, "method", "") != "user" and work != (self.scene.width, self.scene.height):
            self.log(f"flows estimated at {work[0]}x{work[1]} (flow_max_pixels {c.flow_max_pixels}) and "
                     f"scaled to the {self.scene.width}x{self.scene.height} frames")
        return dict(flows)

    def _load_between_flows(self) -> List[Dict[int, object]]:
        """The between_flows estimators' flows of the training pairs (cached on disk), for the
        in-between targets; none when the scene brings its own flow (every method reads it)."""
        if self.cfg.between_prob <= 0:
            return []
        out = []
        for m in between_flow_methods(self.cfg):
            f = flow_for_scene(self.scene, method=m, progress=self._flow_progress,
                               max_pixels=self.cfg.flow_max_pixels)
            if f.method == "user":
                return []
            out.append(dict(f))
        if out:
            self.log(f"in-between targets fuse the flows of {', '.join([self.cfg.flow_method] + between_flow_methods(self.cfg))}")
        return out

    def _prepare_targets(self) -> Dict[int, FrameTargets]:
        sc, c = self.scene, self.cfg
        flows = self.flows if c.use_flow else {}
        out = {}
        for k in sc.train_indices:
            f = sc.frames[k]
            pair = flows.get(k)
            valid = None if pair is None else pair.valid
            out[k] = FrameTargets(
                prepare_targets(self.rt, f.image, f.mask, f.depth if c.use_depth else None,
                                None if pair is None else pair.flow, valid),
                next_time=None if pair is None else float(sc.frames[pair.dst].time))
        return out

    # ------------------------------------------------------------------ one step
    def train_step(self, k: int) -> Dict[str, float]:
        """One optimisation step on training frame k.

        One blocking read: before Adam, the read-back of the step's scalars (the loss sums and the
        NaN / Inf flag of the gradients), after which select's count of the live rows and the
        binning's pair count (both copied without blocking) are checked (_step); only a run's
        first selection and binning read their counts to size their buffers.  The camera is
        uploaded once (project4d; project4d_bwd reuses its buffer)."""
        frame, tgt = self.scene.frames[k], self.targets[k]
        return self._step(frame.camera, frame.time, tgt.next_time, tgt.dev, f"frame {k}")

    def train_step_between(self) -> Optional[Dict[str, float]]:
        """One optimisation step at a time between two training frames, supervised by the frame the
        pair's flow predicts there (train/between.py); None when the drawn target has no supervised
        pixel (tool masks cover it: nothing was done).  With between_model after densify_until the
        step's forward renders the flow to the pair's first frame, and the target blends in the
        frames warped along it: one render, read back before the target is made; with
        between_model_splat two more renders at the pair's frames give the motion along which
        the frames are splatted forward."""
        forward = {}

        def model_motion(camera, t: float, t_to: float) -> np.ndarray:
            out = render(self.rt, self.params, camera, t, t_to, select=self.select_live, check=False)
            motion = self.rendered_motion(out)
            # the pair count: on the host already where the motion was read back (host targets),
            # waited for where it stays on the device; an overflowed render is rendered again
            if out.overflowed:
                out = render(self.rt, self.params, camera, t, t_to, select=self.select_live)
                motion = self.rendered_motion(out)
            forward.setdefault("out", out)     # the first render is at the step's own time
            return motion

        use_model = self.cfg.between_model > 0 and self.step >= self.cfg.densify_until
        drawn = self._between.draw(self.rng, model_motion if use_model else None, self.cfg.between_model, self.step)
        if drawn is None:
            return None
        camera, t, dev = drawn
        return self._step(camera, t, None, dev, f"time {t:.4f}", out=forward.get("out"))   # None: nothing supervised

    def schedule_step(self, order: List[int]):
        """One step as the schedule draws it (train's loop; benchmarks/bench_train_loop.py times it):
        an in-between step with chance between_prob(step), else, or where the in-between target
        supervises nothing, a step on a training frame drawn uniformly from order.  ("between",
        its loss parts) or ("plain", its loss parts)."""
        if self._between and self.rng.random() < self.between_prob(self.step):
            parts = self.train_step_between()      # an in-between time (train/between.py)
            if parts is not None:
                return "between", parts
        return "plain", self.train_step(order[int(self.rng.integers(len(order)))])

    @property
    def select_live(self) -> bool:
        """Steps render and differentiate only the Gaussians alive at their time (ops/select.py)
        when Adam leaves the culled ones alone anyway (adam_skip_culled): the same updates, for
        a fraction of the per-Gaussian work ($ENDOWAVE_NO_SELECT=1 turns it off, for benchmarks)."""
        return bool(self.cfg.adam_skip_culled) and select_enabled()

    def rendered_motion(self, out):
        """[H, W, 2]: the flow channels of a render, where each pixel's Gaussians lie at t_flow: a
        device array where the in-between targets are built on the device, else read back."""
        if getattr(self, "_between", None) is not None and self._between.device is not None:
            return motion_on_device(self.rt, out.features, FLOW.start)
        return out.features.get()[..., FLOW]

    def _step(self, camera, t: float, t_next: Optional[float], dev, what: str, out=None) -> Optional[Dict[str, float]]:
        """render at t (flow to t_next) -> losses against dev (DeviceTargets) -> adjoints -> Adam.
        out: the step's forward when it was rendered already (train_step_between).
        The render waits for neither its live-row count nor its pair count: the read-back is the
        step's wait, and where the rows or the pairs overflowed their buffers (ops/select.py,
        ops/binning.py) the step is done again from a checked render before anything is changed (the densification statistics are accumulated
        after the read-back for that).  Targets whose supervised pixel count stayed on the device
        (device_losses.device_targets) come back with it: where it is 0 the step is dropped there,
        nothing changed, and None returned (as the sampler's draw returns None for host targets)."""
        if out is None:
            out = render(self.rt, self.params, camera, t, t_next, select=self.select_live, check=False)  # forward
        if self._defer:
            return self._step_enqueued(out, dev, what)
        while True:
            pending = self.losses_enqueue(out, dev)                                      # losses
            grads = render_backward(self.rt, self.params, out, pending.v_features,       # adjoints
                                    deterministic=True if self.cfg.deterministic else None,
                                    sh_factors=True)   # v_sh as factors: Adam forms it, the guard checks them
            host = read_back(self.rt, {**pending.sums, "nonfinite": nonfinite_flag(self.rt, grads.values())})
            if "supervised" in host and int(host["supervised"][0]) == 0:
                return None            # an in-between target that supervises nothing: no step
            if not out.overflowed:     # the pair count came back before the read-back did: no wait
                break
            out = render(self.rt, self.params, camera, t, t_next, select=self.select_live)   # checked
        accumulate_stats(self.rt, out, self.stats)
        total, parts = pending.finish(host)
        self._check_finite(total, bool(host["nonfinite"][0]), what)
        self.adam.step({name[2:]: v for name, v in grads.items()}, self.group_lrs(self.step),  # Adam (v_means -> means)
                       visible=out.proj.radius if self.cfg.adam_skip_culled else None,
                       rows=None if out.live is None else out.live.rows)
        self.step += 1
        return parts

    def _step_enqueued(self, out, dev, what: str) -> PendingStep:
        """_step's losses, adjoints, statistics and Adam enqueued behind a gate instead of a wait
        (module docstring): the step's read-back is enqueued and returned, not waited for."""
        pending = self.losses_enqueue(out, dev)                                         # losses
        grads = render_backward(self.rt, self.params, out, pending.v_features,          # adjoints
                                deterministic=True if self.cfg.deterministic else None, sh_factors=True)
        grads_bad = nonfinite_flag(self.rt, grads.values())
        loss_bad = nonfinite_flag(self.rt, [a for a in pending.sums.values() if a.dtype == np.float32])
        supervised = getattr(getattr(dev, "dev", dev), "supervised", None)
        step_gate(self.rt, self._skip, grads_bad, loss_bad, rows=None if out.live is None else out.live.count,
                  pairs=out.binned.pairs, supervised=supervised)                     # the gate
        accumulate_stats(self.rt, out, self.stats, skip=self._skip)
        self.adam.step({name[2:]: v for name, v in grads.items()}, self.group_lrs(self.step),  # Adam
                       visible=out.proj.radius if self.cfg.adam_skip_culled else None,
                       rows=None if out.live is None else out.live.rows, skip=self._skip)
        self.step += 1
        read = PendingRead(self.rt, {**pending.sums, "nonfinite": grads_bad, "skip": self._skip})
        return PendingStep(read, pending.finish, out, what, self.step)

    def _settle(self, p: PendingStep) -> Dict[str, float]:
        """A deferred step's loss parts, once its read-back is in (raises StepSkipped where its
        gate says it was not applied for a reason that doing it again clears, TrainingDiverged where
        it was not finite)."""
        host = p.read.result()
        for count in (p.out.binned.pairs, None if p.out.live is None else p.out.live.count):
            if count is not None:
                count.value()          # copied before the read-back: the capacities learn the count
        if int(host["skip"][0]) & (GATE_ROWS | GATE_PAIRS | GATE_SUPERVISED):
            raise StepSkipped(p.what)
        total, parts = p.finish(host)
        self._check_finite(total, bool(host["nonfinite"][0]), p.what, step=p.step - 1)
        return parts

    def _host_state(self) -> HostState:
        sampler = getattr(self, "_between", None)
        return HostState(self.rng.bit_generator.state, self.step, self.adam.step_count,
                         None if not sampler else sampler.kept_motion())

    def _rewind(self, state: HostState) -> None:
        """Back to the host state before a skipped step, the device's gate cleared: the steps
        skipped on the device changed nothing there."""
        self.rng.bit_generator.state = state.rng
        self.step, self.adam.step_count = state.step, state.adam_steps
        if state.motion is not None:
            self._between.keep_motion(state.motion)
        self._skip.fill(0)

    def _redo(self, order: List[int]):
        """schedule_step, waiting for the step's outcome (a skipped step done again)."""
        defer, self._defer = self._defer, False
        try:
            return self.schedule_step(order)
        finally:
            self._defer = defer

    def _wait_after(self, s: int, budget) -> bool:
        """Whether the loop needs step s's outcome before it enqueues the next step."""
        c = self.cfg
        return bool(s % c.log_every == 0 or s >= c.iterations
                    or (c.densify_from <= s <= c.densify_until and s % c.densify_every == 0)
                    or (s > 0 and s % c.opacity_reset_every == 0 and s < c.densify_until)
                    or (c.eval_every and s % c.eval_every == 0)
                    or (c.checkpoint_every and s % c.checkpoint_every == 0)
                    or (budget is not None and budget.planned is None))

    def losses_enqueue(self, out, dev):
        """The step's losses against dev (device_losses.DeviceTargets; a FrameTargets is accepted
        too) enqueued on the device (train/device_losses.py): a PendingLosses with the gradient image
        v_features [H, W, C] and the sums the host reads back."""
        dev = getattr(dev, "dev", dev)
        channels = {"depth": DEPTH, "flow": FLOW.start}
        return image_losses_enqueue(self.rt, out.features, dev, self.cfg, channels, self.wavelet_config)

    def losses_and_gradient(self, out, tgt: FrameTargets):
        """Total loss, its parts (and the training PSNR), and the gradient image v_features
        [H, W, C]: losses_enqueue, then its sums read back (benchmarks/bench_train_step.py times it)."""
        pending = self.losses_enqueue(out, tgt)
        total, parts = pending.finish(read_back(self.rt, pending.sums))
        return total, parts, pending.v_features

    @property
    def wavelet_config(self):
        """The wavelet loss's settings (TrainConfig wavelet_*), made once per trainer."""
        if not hasattr(self, "_wcfg"):
            self._wcfg = self.cfg.wavelet_config()
        return self._wcfg

    def _check_finite(self, total: float, grads_nonfinite: bool, what: str, step: Optional[int] = None):
        bad = [] if math.isfinite(total) else ["loss"]
        if grads_nonfinite:
            bad.append("gradients")
        if bad:
            raise self._run.fail(self, TrainingDiverged(
                f"step {self.step if step is None else step} ({what}): non-finite {', '.join(bad)}; the step was not applied. "
                f"Try lower learning rates"))

    # ------------------------------------------------------------------ density control
    def densify(self):
        """3DGS density control in 4D on the host: clone, split (children sampled in space-time), prune."""
        self._run.check_parameters(self)     # non-finite or runaway parameters stop the run here
        info: Dict[str, object] = {}
        new_g, source = densify_and_prune(
            download(self.params), self.stats["grad_accum"].get(), self.stats["count"].get(),
            self.stats["max_radius"].get(), self.cfg, self.extent,
            prune_big=self.step > self.cfg.opacity_reset_every, stats=info)
        for k in self.density_counts:
            self.density_counts[k] += int(info[k])
        order = temporal_row_order(new_g)   # the rows alive at one time together (a permutation)
        self.set_gaussians(new_g.take(order),
                           moment_source_index(source[order], info["is_new"][order]))  # new rows: zero moments

    def set_gaussians(self, g: Gaussians, source_index: np.ndarray):
        """Replace the parameters; row i's Adam moments come from old row source_index[i] (< 0: zero)."""
        self.params = upload(self.rt, g)
        self._average = None      # its rows are not these
        self.adam.remap(self.params, source_index)
        self._reset_stats()

    def reset_opacity(self):
        """3DGS opacity reset, on the device: opacity = min(opacity, logit(opacity_reset_value)) in
        place, and the opacity group's Adam moments zeroed (as 3DGS).  The other parameters and
        moments and the densification statistics are kept, as in 3DGS: the reset lowers opacities,
        it does not restart the gradient statistics that choose what to densify."""
        opacity_reset(self.rt, self.params["opacity"], np.float32(logit(self.cfg.opacity_reset_value)))
        self.adam.reset_moments("opacity")

    def average_step(self) -> None:
        """After a step is enqueued: its parameters enter the late steps' mean when it is due
        (train/average.py); the first step of the window starts it."""
        if self.step < average_start(self.cfg):
            return
        if self._average is None:
            self._average = ParameterAverage(self.rt, self.params, self.step)
        elif self._average.due(self.step):
            self._average.add(self.params)

    def _use_average(self) -> Optional[Dict[str, object]]:
        """At the end of a run: the last step's figures, then the mean written into the parameters
        (None where nothing was averaged)."""
        a = self._average
        if a is None or a.count < 2:
            return None
        last = self.evaluate()
        a.copy_to(self.params)
        self._average = None
        return {"from_step": a.first, "snapshots": a.count,
                "last_step": {k: last[k] for k in ("psnr", "psnr_masked", "ssim") if k in last}}

    # ------------------------------------------------------------------ evaluation, checkpoints
    def evaluate(self) -> Dict[str, float]:
        """Test-frame PSNR (both forms) and SSIM; LPIPS and FPS are left to `endowave-cl eval`."""
        return evaluate_run(self.rt, self.params, self.scene, fps_runs=0, with_lpips=False)

    def save(self):
        """Checkpoint after the divergence guard passed; keeps the two newest and the best
        (train/run_folder.py), and writes train_log.json."""
        return self._run.save(self)

    # ------------------------------------------------------------------ time budget
    def _start_budget(self):
        """A BudgetPlan when cfg.minutes is set (train/budget.py), else None."""
        c = self.cfg
        if not c.minutes > 0:
            return None
        # the final checkpoint and evaluation render every test frame once: a few steps' worth
        # (twice where the last step is scored before the averaged parameters replace it)
        renders = len(self.scene.test_indices) * (2 if c.average_last > 0 else 1)
        reserve = min(0.1 * c.minutes * 60.0, 5.0 + 0.05 * renders)
        return BudgetPlan.start(c, c.minutes, reserve, t_start=self.t_created)

    def _replan(self, budget, step_times: List[float], bar) -> bool:
        """Re-plan the schedule from the measured step rate (first after MIN_TIMED_STEPS steps,
        then every log interval); True when the plan changed."""
        timed = step_times[WARMUP_STEPS:]
        first = budget.planned is None
        if len(timed) < MIN_TIMED_STEPS or not (first or self.step % self.cfg.log_every == 0):
            return False
        rate = float(np.median(timed[-RATE_WINDOW:]))
        old = budget.planned
        self.cfg = budget.replan(self.cfg, self.step, rate)
        total = budget.planned
        if first:
            c = self.cfg
            bar.write(f"time budget {c.minutes:g} min: planned {total} steps at {rate * 1e3:.0f} ms/step "
                      f"(densify {c.densify_from}-{c.densify_until}, position lr decay over "
                      f"{c.lr_position_steps} steps); re-planned as the step rate changes")
        return total != old

    def _split_build_time(self, loop_seconds: float, step_times: List[float], loop_build0: float,
                          warm_build: float):
        """(training seconds, build seconds) of a session: the builds before the loop (runtime.py
        counts them), the first ETA_WARMUP_STEPS steps' excess over the typical step that follows (a
        driver such as PoCL compiles a kernel at its first launch, so builds hide in those steps),
        and builds timed in the loop after them (a kernel first used at densification)."""
        w = ETA_WARMUP_STEPS
        excess = 0.0
        if len(step_times) > w:
            typical = float(np.median(step_times[w:w + 50]))
            excess = max(0.0, float(sum(step_times[:w])) - w * typical)
        later = getattr(self.rt, "build_seconds", 0.0) - warm_build
        before = loop_build0 - self._build0
        return max(0.0, loop_seconds - excess - later), before + excess + later

    def _write_curves(self, tb, png: bool = False) -> None:
        """RUN/train_curves.csv (and the newest row to TensorBoard; with png, train_curves.png):
        train/curves.py.  A curve file that cannot be written costs a line, not the run."""
        try:
            if tb is not None and self.history:
                tb.add(self.history[-1])
            curves.write_csv(self.run_dir, self.history)
            if png:
                curves.write_png(self.run_dir, self.history, title=f"{self.run_dir.name}: {self.scene.path}")
        except (OSError, ValueError) as e:
            self.log(f"training curves not written: {e}")

    # ------------------------------------------------------------------ the loop
    def train(self, progress: bool = True) -> Dict[str, float]:
        c = self.cfg
        order = list(self.scene.train_indices)
        bar = progress_bar(total=c.iterations, initial=self.step, disable=not progress, dynamic_ncols=True,
                   desc="train", unit="it")
        t_start = time.perf_counter()
        loop_build0 = warm_build = getattr(self.rt, "build_seconds", 0.0)
        eta_from = self.step + ETA_WARMUP_STEPS   # the rate and time left count the steps after these
        hold_rate(bar)
        budget = self._start_budget()
        tb = TensorBoard(self.run_dir, self.step)   # scalars when tensorboard is installed; the CSV always
        step_times: List[float] = []        # wall time per step of the loop (a deferred step's
                                             # enqueue and the wait for the step before it)
        ema = self._run.ema                  # restored on resume
        pending = None                       # (kind, PendingStep, HostState): enqueued, not read yet
        defer = deferred_steps()

        def running_mean(parts):
            # the log and the divergence guard follow the training frames only
            return parts if ema is None else {key: 0.9 * ema.get(key, v) + 0.1 * v for key, v in parts.items()}

        def settle_pending() -> bool:
            """Read the step enqueued last and do its bookkeeping (never a log step: _wait_after);
            a step skipped on the device is done again from its state, waiting for it.  True
            where it was: the step enqueued behind it, skipped with it, is to be drawn again."""
            nonlocal ema, warm_build, pending
            kind, step, state = pending
            pending = None
            try:
                parts, s, redone = self._settle(step), step.step, False
            except StepSkipped:
                self._rewind(state)
                (kind, parts), s, redone = self._redo(order), self.step, True
                self.redone_steps += 1
            if kind == "plain":
                ema = running_mean(parts)
            self._run.after_step(self, s, ema)
            bar.update(1)
            if s == eta_from:
                restart_rate(bar)
                warm_build = getattr(self.rt, "build_seconds", 0.0)
            return redone

        while self.step < c.iterations:
            out_of_time = budget is not None and budget.out_of_time()
            if pending is not None and (out_of_time or self._run.stop.requested is not None):
                settle_pending()
            self._run.poll(self)             # SIGINT / SIGTERM: save at this step boundary and stop
            if out_of_time:
                bar.write(f"time budget of {c.minutes:g} min reached at step {self.step}")
                break
            t_step = time.perf_counter()
            # a step whose outcome the loop needs at once waits for it, the step before it read first
            # (a blocking step is not gated: it must not follow a skipped one)
            self._defer = defer and not self._wait_after(self.step + 1, budget)
            if pending is not None and not self._defer:
                settle_pending()
            state = self._host_state() if self._defer else None
            kind, result = self.schedule_step(order)
            self.average_step()
            if pending is not None and settle_pending():   # the step before, read now this one is enqueued
                step_times.append(time.perf_counter() - t_step)
                continue                     # this step was skipped behind it: it is drawn again
            if isinstance(result, PendingStep):   # a deferred step (a step done at once returns its parts)
                pending = (kind, result, state)
                step_times.append(time.perf_counter() - t_step)
                continue
            step_times.append(time.perf_counter() - t_step)
            if kind == "plain":
                ema = running_mean(result)
            s = self.step
            if c.densify_from <= s <= c.densify_until and s % c.densify_every == 0:
                self.densify()
            if s > 0 and s % c.opacity_reset_every == 0 and s < c.densify_until:   # as 3DGS: not at its end
                self.reset_opacity()
                self._run.guard.reset_reference(s)   # the PSNR dips on purpose
            if budget is not None and self._replan(budget, step_times, bar):
                c = self.cfg                             # the re-planned schedule
                bar.total = c.iterations
            if (s % c.log_every == 0 or s == c.iterations) and ema is not None:
                bar.set_postfix(loss=f"{ema['total']:.4f}", psnr=f"{ema['psnr']:.2f}", N=len(self.params["means"]))
                self.history.append({"step": s, **{k2: float(v) for k2, v in ema.items()},
                                     "gaussians": len(self.params["means"]),
                                     "step_ms": 1e3 * float(np.median(step_times[-c.log_every:]))})
                self._write_curves(tb)
            self._run.after_step(self, s, ema)   # divergence guard (PSNR collapse; parameters at log steps)
            if c.eval_every and s % c.eval_every == 0 and s < c.iterations:
                m = self.evaluate()
                bar.write(f"step {s}: {self.scene.split} PSNR {m['psnr']:.2f} dB (masked {m['psnr_masked']:.2f}), "
                          f"SSIM {m['ssim']:.3f}, {len(self.params['means'])} Gaussians")
            if c.checkpoint_every and s % c.checkpoint_every == 0:
                self.save()
            bar.update(1)
            if self.step == eta_from:
                restart_rate(bar)             # the time left from here on
                warm_build = getattr(self.rt, "build_seconds", 0.0)
        if pending is not None:               # a plan cut short under a step enqueued last
            settle_pending()
        self._defer = False
        bar.close()
        seconds, build_seconds = self._split_build_time(time.perf_counter() - t_start, step_times,
                                                        loop_build0, warm_build)
        averaged = self._use_average()
        self.save()
        metrics = self.evaluate()
        if averaged is not None:
            metrics["averaged"] = averaged
            self.log(f"the saved model is the mean of {averaged['snapshots']} snapshots from step "
                     f"{averaged['from_step']}: {self.scene.split} PSNR {metrics['psnr']:.2f} dB "
                     f"(the last step alone {averaged['last_step']['psnr']:.2f})")
        metrics.update({"step": self.step, "gaussians": len(self.params["means"]), "train_seconds": seconds,
                        "redone_steps": self.redone_steps, "density_control": dict(self.density_counts),
                        "build_seconds": build_seconds})
        tb.close()
        self._write_curves(None, png=True)
        self._run.finish(self, metrics)     # train_log.json (strict JSON), release the run folder lock
        return metrics
