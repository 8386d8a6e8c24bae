"""The in-between target built on the device (issue 60): train/between.py's flow prediction and the
model's blend, chained from the kernels of ops/between.py, into device memory, with no host work
and no read in the step: the supervised pixel count (the loss's denominator) stays on the device
too, and the losses take their colour weights for it from a table there (device_losses.device_targets)
and read it back with their sums.

What stays on the host is made once, before training: the frames and the pairs' flows are uploaded
once, the estimators' fused flows (consistent_flows) and the curved paths' Bends are made once per
pair.  Every step then enqueues, per estimator, one backward warp of the pair's frames along its
(curved) paths; the fusion; the two frames' forward splats along the fused flows and their
reversed pushes; and after densify_until the model's warp along the motion its forward rendered,
the splats along the pair's kept motion, and the blend.

With between_levels the fraction s is on the sampler's grid as on the host, and the target is built
at every draw (the host keeps float16 copies per grid point instead, within 5e-4 of these).

The host path (train/between.py between_target) is the reference:
tests/kernels/test_between_kernels.py compares the two.  It builds the target where no device is
given (the Teacher), and where between.targets_on_device says so: by default on a CPU device, where
the same cores would run the kernels and OpenCV's SIMD remap is the faster of the two
(ENDOWAVE_BETWEEN_TARGET=device|host chooses; benchmarks/bench_train_loop.py --both-paths)."""
from __future__ import annotations

from typing import Dict, List, Optional, Tuple

import numpy as np
import pyopencl.array as cla

from ..ops.between import (Frame, Path, between_fuse, between_mix, between_push, between_splat, between_warp,
                           check_int64_atomics, frame_on_device, stack)


def motion_on_device(rt, features, flow_channel: int):
    """[H, W, 2] device array: the flow channels (flow_channel, flow_channel + 1) of a render's
    feature image [H, W, C], copied on the device (one rectangular copy, no kernel)."""
    h, w, c = (int(v) for v in features.shape)
    out = rt.empty((h, w, 2))
    rt.cl.enqueue_copy(rt.queue, out.data, features.base_data, src_origin=(4 * flow_channel + int(features.offset), 0),
                       dst_origin=(0, 0), region=(8, h * w), src_pitches=(4 * c,), dst_pitches=(8,))
    return out


class DeviceTarget:
    """The device half of a BetweenSampler (train/between.py): its frames, flows, fused flows and
    Bends on the device, and ``build``, the target of one draw."""

    def __init__(self, rt, sampler, radius: int, tau: float, min_weight: float, pair_bend, colour: str = "cubic"):
        """sampler: the BetweenSampler; radius, tau: fused_interpolation's FUSE_RADIUS, FUSE_TAU;
        min_weight: SPLAT_MIN_WEIGHT; pair_bend: between.pair_bend; colour: how the frames' colour
        is sampled, between.SAMPLER (these passed in: between.py imports this module)."""
        check_int64_atomics(rt)
        self.rt, self.b = rt, sampler
        self.radius, self.tau, self.min_weight, self.colour = radius, tau, min_weight, colour
        self._frames: Dict[int, Frame] = {}
        self._flows: Dict[int, object] = {}            # id(host array) -> device copy (kept with the host array)
        self._keep: List[np.ndarray] = []
        b = sampler
        self.fused = b.flow_splat
        self._pair_fused: Dict[int, Tuple[object, object]] = {}
        self._bends: Dict[int, object] = {}
        for index, pair in enumerate(b.pairs):       # everything that depends on the pair alone, once
            for k in (pair.src, pair.dst):
                self.frame(k)
            for p in (pair, *b.extra(pair)):
                self.flow(p.flow)
                self.flow(p.flow_bw)
            if self.fused:
                f, fb = b._fused(index)
                self._pair_fused[index] = (self.flow(f), self.flow(fb))
            if b.path == "quadratic":
                self._bends[index] = pair_bend(b.scene, b.pairs, index, lambda p: [p, *b.extra(p)],
                                               b._fused if self.fused else None)

    def frame(self, k: int) -> Frame:
        """Frame k's image, range and mask on the device, uploaded once."""
        if k not in self._frames:
            f = self.b.scene.frames[k]
            self._frames[k] = frame_on_device(self.rt, f.image, f.mask)
        return self._frames[k]

    def flow(self, a: Optional[np.ndarray]):
        """A host flow [H, W, 2] on the device, uploaded once (None stays None)."""
        if a is None:
            return None
        key = id(a)
        if key not in self._flows:
            self._flows[key] = cla.to_device(self.rt.queue, np.ascontiguousarray(a, np.float32))
            self._keep.append(a)                     # the id stays this array's
        return self._flows[key]

    def _motion(self, m):
        """A motion given as a host array [H, W, 2] (uploaded) or a device one (as it is)."""
        return self.flow(m) if isinstance(m, np.ndarray) else m

    def _path(self, flow, s: float, span: float, outer=None, outer_span: float = 0.0) -> Path:
        """between.path_displacement as a Path over device arrays (flow, outer: host arrays)."""
        if outer is None or outer_span * span >= 0.0:
            return Path(self.flow(flow), float(np.float32(s)))
        tau = s * span
        a = tau * (tau - outer_span) / (span * (span - outer_span))
        b = tau * (tau - span) / (outer_span * (outer_span - span))
        return Path(self.flow(flow), a, self.flow(outer), b)

    def _paths(self, index: int, flow, flow_bw, s: float, h: Optional[int], fused_dev=None) -> Tuple[Path, Path]:
        """(g0, g1) of pair index at s for source h's flows (h None: the fused flows), straight or
        along the pair's Bend, as Bend.paths and between._flow_prediction form them."""
        bend = self._bends.get(index)
        if bend is None:
            if fused_dev is not None:
                return Path(fused_dev[0], float(np.float32(s))), Path(fused_dev[1], float(np.float32(1.0 - s)))
            return Path(self.flow(flow), float(np.float32(s))), Path(self.flow(flow_bw), float(np.float32(1.0 - s)))
        before, after = bend.fused if h is None else (bend.before[h], bend.after[h])
        return (self._path(flow, s, bend.span, before, bend.before_span),
                self._path(flow_bw, 1.0 - s, -bend.span, after, bend.after_span))

    def flow_prediction(self, index: int, s: float):
        """(image [H, W, 3], weight [H, W]) device arrays: between._flow_prediction of pair index
        at fraction s."""
        b, rt = self.b, self.rt
        pair = b.pairs[index]
        f0, f1 = self.frame(pair.src), self.frame(pair.dst)
        wa, wb = float(np.float32(1.0 - s)), float(np.float32(s))
        sources = [pair, *b.extra(pair)]
        hyps = [between_warp(rt, f0, f1, *self._paths(index, p.flow, p.flow_bw, s, h), wa, wb,
                            sampler=self.colour)
                for h, p in enumerate(sources)]
        if len(hyps) == 1:
            image, _, weight = hyps[0]
        else:
            image, weight = between_fuse(rt, *(stack(rt, [x[i] for x in hyps]) for i in range(3)),
                                         self.radius, self.tau, b.fuse)
        if self.fused:
            fl, fl_bw = b._fused(index)
            g0, g1 = self._paths(index, fl, fl_bw, s, None, self._pair_fused[index])
            image = self._push(f0, f1, g0, g1, wa, wb, image)
        return image, weight

    def _push(self, f0: Frame, f1: Frame, g0: Path, g1: Path, wa: float, wb: float, fill):
        """The two frames pushed forward along g0 and g1 (reversed splats), fill where neither reaches."""
        acc0 = between_splat(self.rt, g0, f0)
        acc1 = between_splat(self.rt, g1, f1)
        return between_push(self.rt, acc0, acc1, f0, f1, wa, wb, fill, self.min_weight, self.colour)

    def build(self, index: int, s: float, model_disp=None, model_weight: float = 0.0, model_fwd=None):
        """(image [H, W, 3], weight [H, W], count int32 [1]) device arrays: between_target of pair
        index at fraction s (BetweenSampler.target's arguments, the motions host or device [H, W, 2]
        arrays; model_fwd: ((g0, factor), (g1, factor)), factor None for 1); count: the supervised
        pixels (weight > 0), for the loss's denominator."""
        image, weight = self.flow_prediction(index, s)
        if model_disp is None or not model_weight > 0.0:
            return between_mix(self.rt, image, weight)
        pair = self.b.pairs[index]
        f0, f1 = self.frame(pair.src), self.frame(pair.dst)
        wa, wb = float(np.float32(1.0 - s)), float(np.float32(s))
        disp = self._motion(model_disp)
        # d0 = disp, d1 = disp -(1 - s) / s as blend_model_prediction forms them; a Path samples at p - g
        c = float(np.float32(-(1.0 - s) / s)) if s > 0.0 else 0.0
        model, _, ok = between_warp(self.rt, f0, f1, Path(disp, -1.0), Path(disp, -c), wa, wb, sampler=self.colour)
        if model_fwd is not None:
            g0, g1 = (Path(self._motion(g), 1.0 if c is None else float(c)) for g, c in model_fwd)
            model = self._push(f0, f1, g0, g1, wa, wb, model)
        return between_mix(self.rt, image, weight, model, model_weight, ok)
