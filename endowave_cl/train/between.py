"""Supervision at times between two training frames, from the training pair's own flow.

A training step renders only at the training frames' times, so nothing says what the model shows
in between: its Gaussians may fit each frame on its own (noise and compression artefacts too) and
blend those fits between frames, which is what the test frames then see (research/QUALITY.md).  The
pseudo ground-truth flow of every training pair (k, k') is known before training, so the frame at a
time fraction s between them can be predicted, as a flow interpolator does:

    W0(p) = I_k(p - s F_kk'(p)),  W1(p) = I_k'(p - (1 - s) F_k'k(p)),  target = (1 - s) W0 + s W1

(the DIS baseline's warp, ``baselines.dis_interpolations``; the frames are sampled between
pixels bicubically, SAMPLER: bilinear sampling at the half-pixel offsets of a midway warp averages
neighbouring pixels and teaches a blurred frame, research/QUALITY.md finding 10).
Every pixel is supervised, also where the flow failed its forward-backward check: there the target degrades towards a blend of
the two frames, which still bounds what the model may show in between (supervising only the
trusted pixels measured 0.25 dB lower on the pulling frames, research/QUALITY.md).  With tool masks,
only pixels that show tissue in both warped frames are supervised.  The step uses the colour
losses (L1, D-SSIM, wavelet) and no depth or flow term.  Pairs whose two cameras differ are not
used: an image-space warp predicts nothing for a moving camera.

Several flow estimators (``between_flows``): each estimator's flows give one hypothesis (W0_h,
W1_h) of the frame at s.  Where a hypothesis's flow is right, its two warps show the same tissue;
where it is wrong, they disagree.  ``fused_interpolation`` weighs the hypotheses per pixel by that
disagreement, E_h = box mean over (2 FUSE_RADIUS + 1)^2 pixels of sum_c |W0_h - W1_h|, with
weights exp(-(E_h - min_h E_h) / FUSE_TAU) normalised over h, and blends their interpolations
(1 - s) W0_h + s W1_h.  No frame at s is needed: the choice uses only the two training frames.
With ``between_fuse = "mean"`` the hypotheses are averaged instead (equal weights where they are
valid): their errors partly cancel, which scores higher PSNR on real video at the price of a
softer frame (research/QUALITY.md finding 20).

The model's own motion (``between_model``, after densify_until): by then the Gaussians' motion is
fitted to every training frame, not to one pair's flow.  The step's forward also renders the flow
channels to the pair's first frame, d0(p) (where the tissue under p at s was at t_k); the means
move linearly in time, so d1 = -(1 - s) / s d0 is where it will be at t_k'.  The two frames warped
along (d0, d1) are a second prediction of the frame at s whose errors differ from the flow
interpolation's, and the target is their blend, (1 - w) flow target + w ((1 - s) I_k(p + d0) +
s I_k'(p + d1)).  On the pulling frames the blend of the two predictions is nearer the held-out
frames than either alone (research/QUALITY.md finding 19).

With ``between_model_splat`` the model's prediction pushes the frames forward instead: two more
renders give the motion the model shows at each frame's own time, g0 from t_k to s and g1 from
t_k' to s, I_k (I_k') is pushed forward along g0 (g1) as below (reversed_splat_interpolation),
and the pixels that neither frame reaches keep the backward prediction above.  At its training
frames the model is fitted closely, so its motion there is better than the motion it renders
between them, and a forward splat leaves a pixel that one frame cannot see to the other
(research/QUALITY.md finding 20).

How a forward splat makes its image: the displacement is splatted, not the colour (sharing each
pixel's colour bilinearly among the four pixels around where it lands would average neighbouring
pixels at fractional offsets, the blur of a bilinear backward warp).  At every pixel q that the
frame reaches, the splatted mean of the displacements of the pixels that land there says where q's
colour comes from, and the frame is sampled there bicubically (reversed_splat); the two frames are
blended with weights (1 - s) and s times how densely each reaches q, at most once, so that what one
frame cannot see (or sees stretched) comes from the other, and a frame whose motion converges at q
does not outweigh the other there (research/QUALITY.md findings 21, 52).  With
``between_flow_splat`` the flows push the frames forward the same way (s F_kk' from the first
frame, (1 - s) F_k'k from the second) instead of sampling them backward, the fused backward
prediction filling the pixels that neither frame reaches.  The frames are pushed once, along the
estimators' flows fused per pixel by how well each returns to its start (``consistent_flows``: forward-backward error), which is as good a
teacher on the pulling frames as pushing every estimator's frames, at a third of the splats
(research/QUALITY.md finding 22).  The fused flows depend on the pair alone and are made once per
pair.

Curved paths (``between_path = "quadratic"``): the flows above move every pixel at constant
velocity between the pair's frames.  Tissue that is pulled speeds up and slows down, and the
training frames on either side of the pair say how: the first frame's flow to the training frame
before it, and the second frame's flow to the one after it.  Each pixel then moves along the
parabola through its three positions (path_displacement, as quadratic video interpolation does,
Xu et al., NeurIPS 2019), in every warp and push above; a side with no training frame beyond the
pair (a sequence end, another camera) keeps the straight path.  The bending flows are made once per
pair (Bend).
"""
from __future__ import annotations

import functools
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np

from .. import env
from ..data.flow import flow_for_scene
from ..warp import sample_displaced, splat_forward
from .between_device import DeviceTarget
# the in-between modes' names are settings' values, listed in config.py (read from here too)
from .config import FUSE_MODES, PATHS, S_DISTRIBUTIONS, between_flow_methods  # noqa: F401
from .device_losses import device_targets, prepare_targets


# how the frames are sampled between pixels (warp.SAMPLERS), in every warp and push of the target,
# host and device: bicubically (bilinear sampling averages neighbouring pixels at half-pixel offsets
# and teaches a blurred frame, research/QUALITY.md finding 10; the tool masks are sampled
# bilinearly).  "lanczos" is the other sampler the device target has: a sharper teacher, level for
# the model on the real scenes at twice the sampling cost (finding 53)
SAMPLER = "cubic"
# fused_interpolation: half-width (px) of the box over which a hypothesis's two warps are compared,
# and the disagreement (sum of the three channels' absolute differences, images in [0, 1]) at which
# a hypothesis's weight falls by a factor e against the best one's
FUSE_RADIUS = 3
FUSE_TAU = 0.02
# consistent_flows: the forward-backward error (px) at which an estimator's weight falls by a
# factor e against the most consistent one's: a flow that fails to return by several pixels is left
# out, smaller differences are averaged (research/QUALITY.md finding 52)
PUSH_TAU = 4.0
# between_levels: the most host memory the flow predictions kept per grid point may take (bytes);
# past it the predictions of further (pair, grid point)s are made at every draw
TARGET_CACHE_BYTES = 2 << 30
# where the in-between targets are built: "device" (train/between_device.py), "host" (OpenCV and
# numpy, the reference path) or "auto": the device on a GPU, the host on a CPU device, where the
# same cores run both and OpenCV's remap outruns the kernels (benchmarks/bench_train_loop.py
# --both-paths)
ENV_BETWEEN_TARGET = "ENDOWAVE_BETWEEN_TARGET"
# reversed_splat_interpolation: a target pixel with less splatted weight than this (of the one a
# pixel has that is reached by one source pixel exactly) keeps the backward prediction
SPLAT_MIN_WEIGHT = 0.05


def path_displacement(flow: np.ndarray, s: float, span: float, outer: Optional[np.ndarray] = None,
                      outer_span: float = 0.0) -> np.ndarray:
    """[H, W, 2]: where a frame's pixels are, relative to where they start, at fraction s of the
    time span (signed) to the pair's other frame; flow [H, W, 2] their displacement at the end of
    span.  outer [H, W, 2]: their displacement to a frame outer_span away on the other side in time
    (of the opposite sign to span); with it the pixel moves along the parabola through its three
    positions (Lagrange's form through tau = 0, span and outer_span, at tau = s span), without it
    s flow."""
    flow = np.asarray(flow, np.float32)
    if outer is None or outer_span * span >= 0.0:
        return np.float32(s) * flow
    tau = s * span
    a = tau * (tau - outer_span) / (span * (span - outer_span))           # weight of flow
    b = tau * (tau - span) / (outer_span * (outer_span - span))           # weight of outer
    return cv2.addWeighted(flow, a, np.asarray(outer, np.float32), b, 0.0)   # one pass over the pixels


@dataclass
class Bend:
    """What bends a pair's paths into parabolas (between_path "quadratic", module docstring).
    span: t_k' - t_k; before_span: t_before - t_k (< 0), after_span: t_after - t_k' (> 0).
    before[h] / after[h] [H, W, 2] or None: per flow source h (between_target's pair, then its
    extra), the displacement of frame k's pixels to the training frame before the pair and of
    frame k''s pixels to the one after it; fused: the same of consistent_flows (between_flow_splat),
    or (None, None).  None marks a side with no such frame: that side's path is straight."""
    span: float
    before_span: float
    after_span: float
    before: List[Optional[np.ndarray]]
    after: List[Optional[np.ndarray]]
    fused: Tuple[Optional[np.ndarray], Optional[np.ndarray]] = (None, None)

    def paths(self, flow: np.ndarray, flow_bw: np.ndarray, s: float, h: Optional[int] = None):
        """(g0, g1) [H, W, 2] each: where frame k's and frame k''s pixels are at fraction s,
        relative to where they start, for source h's flows (h None: the fused flows)."""
        before, after = self.fused if h is None else (self.before[h], self.after[h])
        return (path_displacement(flow, s, self.span, before, self.before_span),
                path_displacement(flow_bw, 1.0 - s, -self.span, after, self.after_span))


def pair_bend(scene, pairs: Sequence[object], index: int, sources, fused=None) -> Optional[Bend]:
    """The Bend of pairs[index] (training pairs in frame order, as usable_pairs gives them), or None
    where neither side has a training frame beyond the pair.  sources(pair) -> the FlowPairs of a
    pair's frames, one per estimator in between_target's order; fused(i) -> consistent_flows of
    pairs[i], or None when the frames are not pushed along fused flows."""
    pair = pairs[index]
    prev = pairs[index - 1] if index > 0 and pairs[index - 1].dst == pair.src else None
    nxt = pairs[index + 1] if index + 1 < len(pairs) and pairs[index + 1].src == pair.dst else None
    if prev is None and nxt is None:
        return None
    n = len(sources(pair))
    before = [p.flow_bw for p in sources(prev)] if prev is not None else []
    after = [p.flow for p in sources(nxt)] if nxt is not None else []
    before = before if len(before) == n else [None] * n
    after = after if len(after) == n else [None] * n
    t = [float(scene.frames[i].time) for i in (pair.src, pair.dst)]
    t_before = float(scene.frames[prev.src].time) if prev is not None else t[0]
    t_after = float(scene.frames[nxt.dst].time) if nxt is not None else t[1]
    fused_bend = (None, None)
    if fused is not None:
        fused_bend = (fused(index - 1)[1] if prev is not None else None,
                      fused(index + 1)[0] if nxt is not None else None)
    return Bend(t[1] - t[0], t_before - t[0], t_after - t[1], before, after, fused_bend)


def frames_beyond(scene, src: int, dst: int) -> Tuple[Optional[int], Optional[int]]:
    """(before, after): the nearest training frames before frame src and after frame dst that share
    frame src's camera (None where there is none, or where dst's camera differs)."""
    cam = scene.frames[src].camera
    if not _same_camera(scene.frames[dst].camera, cam):
        return None, None
    train = [i for i in scene.train_indices if _same_camera(scene.frames[i].camera, cam)]
    return (max((i for i in train if i < src), default=None), min((i for i in train if i > dst), default=None))


def bend_around(scene, sources: Sequence[object], methods: Sequence[str], flows_of, fused: bool = False) -> Optional[Bend]:
    """The Bend of a pair of frames that need not be a training pair (tools that score a target at a
    held-out frame): sources, the pair's FlowPairs (or alike: src, dst, flow, flow_bw) per estimator
    in between_target's order, methods their estimators' names; flows_of(a, b, method) -> [H, W, 2],
    frame a's flow to frame b.  The frames beyond the pair are the nearest training frames before its
    first and after its second frame with the same camera; fused: bend the fused flows too."""
    src, dst = sources[0].src, sources[0].dst
    before, after = frames_beyond(scene, src, dst)
    made = {(src, dst): list(sources)}

    def pair(a, b):
        made[(a, b)] = [SimpleNamespace(src=a, dst=b, flow=flows_of(a, b, m), flow_bw=flows_of(b, a, m)) for m in methods]
        return made[(a, b)][0]

    pairs = ([pair(before, src)] if before is not None else []) + [sources[0]]
    pairs += [pair(dst, after)] if after is not None else []
    index = 1 if before is not None else 0
    return pair_bend(scene, pairs, index, lambda p: made[(p.src, p.dst)],
                     (lambda i: consistent_flows(made[(pairs[i].src, pairs[i].dst)])) if fused else None)


def disagreement(warps: Sequence[Tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """[K, H, W]: per hypothesis (W0_h, W1_h), the box mean over (2 FUSE_RADIUS + 1)^2 pixels of
    sum_c |W0_h - W1_h|: how far its two warped frames disagree around each pixel."""
    size = (2 * FUSE_RADIUS + 1,) * 2
    channel_sum = np.ones((1, 3), np.float32)      # cv2.transform: [H, W, 3] -> [H, W] sum
    return np.stack([cv2.blur(cv2.transform(cv2.absdiff(w0, w1), channel_sum), size) for w0, w1 in warps])


def fused_interpolation(warps: Sequence[Tuple[np.ndarray, np.ndarray]], s: float,
                        valid: Optional[Sequence[np.ndarray]] = None,
                        mode: str = "agree") -> Tuple[np.ndarray, np.ndarray]:
    """(image [H, W, 3], weight [H, W]) fused from K hypotheses of the frame at fraction s (module
    docstring).  warps: [(W0, W1)] per hypothesis, frame 0 and frame 1 warped to s ([H, W, 3]
    each); valid: [H, W] per hypothesis, 0 where it must not be used (tool masks); weight is 1
    where at least one hypothesis is valid.  mode (FUSE_MODES): "agree" weighs the hypotheses by
    how well their two warps agree, "mean" gives the valid ones equal weights."""
    if mode == "mean":
        err = np.zeros((len(warps),) + warps[0][0].shape[:2], np.float32)              # [K, H, W]
    else:
        err = disagreement(warps)                                                       # [K, H, W]
    any_ok = np.ones(err.shape[1:], bool)
    if valid is not None:
        ok = np.stack([np.asarray(v) > 0 for v in valid])
        any_ok = ok.any(0)                                                              # [H, W]
        ok |= ~any_ok        # no valid hypothesis: fuse them all (the pixel is not supervised)
        err[~ok] = np.inf
    w = np.exp((err.min(0) - err) * np.float32(1.0 / FUSE_TAU))                         # [K, H, W]
    w /= w.sum(0)
    image = np.zeros(warps[0][0].shape, np.float32)
    for wk, (w0, w1) in zip(w, warps):
        blend = cv2.addWeighted(w0, 1.0 - s, w1, s, 0.0)
        cv2.accumulateProduct(cv2.cvtColor(wk, cv2.COLOR_GRAY2RGB), blend, image)
    return image, any_ok.astype(np.float32)


def extra_pairs(extra_flows: Sequence[Dict[int, object]], pair) -> List[object]:
    """The FlowPairs of pair's two frames in further estimators' {k: FlowPair} (between_target's extra)."""
    return [f[pair.src] for f in extra_flows if pair.src in f and f[pair.src].dst == pair.dst]


def _same_camera(a, b) -> bool:
    return (a.width == b.width and a.height == b.height
            and np.allclose([a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy])
            and np.allclose(np.asarray(a.viewmat, np.float64), np.asarray(b.viewmat, np.float64), atol=1e-6))


def usable_pairs(scene, flows: Dict[int, object]) -> List[object]:
    """The training pairs (data.flow.FlowPair) whose two frames share the camera, in frame order."""
    return [p for k, p in sorted(flows.items()) if _same_camera(scene.frames[p.src].camera, scene.frames[p.dst].camera)]


def between_target(scene, pair, s: float, extra: Sequence[object] = (),
                   model_disp: Optional[np.ndarray] = None, model_weight: float = 0.0, fuse: str = "agree",
                   model_fwd: Optional[Tuple[np.ndarray, np.ndarray]] = None, flow_splat: bool = False,
                   pushed_flows: Optional[Tuple[np.ndarray, np.ndarray]] = None,
                   bend: Optional[Bend] = None) -> Tuple[np.ndarray, np.ndarray, float]:
    """(image [H, W, 3], weight [H, W], time) of the frame at fraction s in (0, 1) between the pair's
    frames (module docstring); weight 1 where the target is supervised, 0 elsewhere.  The frames are
    sampled bicubically (SAMPLER), the masks bilinearly.  extra: FlowPairs of the same
    two frames from other estimators, fused with the pair's own (fused_interpolation, as fuse
    says: FUSE_MODES).  model_disp
    [H, W, 2]: where each pixel of the model's render at s lies in the pair's first frame (its
    rendered flow to that time); the two frames warped along it (the second along the same motion
    scaled to its time) are blended into the target with model_weight.  model_fwd (g0, g1)
    [H, W, 2] each: where the model moves each pixel of the first and of the second frame by the
    time at s; with it the model's prediction pushes the frames forward along them
    (reversed_splat_interpolation), the backward warps along model_disp filling what neither
    reaches.  flow_splat: the frames are pushed forward too, once, along consistent_flows of all the
    hypotheses (s times the fused flow from the first frame, (1 - s) times the fused flow back from
    the second; pushed_flows: those flows when they were made already), the fused backward
    prediction filling the rest.  bend: the pair's Bend (pair_bend): every flow moves the pixels
    along parabolas instead of straight lines."""
    f0, f1 = scene.frames[pair.src], scene.frames[pair.dst]
    image, weight = _flow_prediction(f0, f1, pair, s, extra, fuse, flow_splat, pushed_flows, bend)
    image, weight = blend_model_prediction(scene, pair, s, image, weight, model_disp, model_weight, model_fwd)
    return image, weight, pair_time(scene, pair, s)


def blend_model_prediction(scene, pair, s: float, image: np.ndarray, weight: np.ndarray,
                           model_disp: Optional[np.ndarray], model_weight: float,
                           model_fwd: Optional[Tuple[np.ndarray, np.ndarray]]):
    """(image, weight): the flow prediction (image, weight) at fraction s blended with the model's
    own prediction as between_target describes (model_disp, model_weight, model_fwd); the
    flow prediction itself where model_disp is None or model_weight is 0."""
    if model_disp is None or not model_weight > 0.0:
        return image, weight
    f0, f1 = scene.frames[pair.src], scene.frames[pair.dst]
    # the Gaussians' means move linearly in time, so the displacement to the second frame is
    # the first one scaled by the ratio of the time steps: -(1 - s) / s (at s = 0 the second
    # frame has no weight)
    d0 = np.asarray(model_disp, np.float32)
    d1 = d0 * np.float32(-(1.0 - s) / s) if s > 0.0 else np.zeros_like(d0)
    w0, w1, ok = _warp_pair(f0, f1, d0, d1)
    model = ((1.0 - s) * w0 + s * w1).astype(np.float32)                           # [H, W, 3]
    if model_fwd is not None:
        model = reversed_splat_interpolation(f0, f1, model_fwd[0], model_fwd[1], s, model)
    image = ((1.0 - model_weight) * image + model_weight * model).astype(np.float32)
    return image, weight * ok


def _flow_prediction(f0, f1, pair, s: float, extra: Sequence[object], fuse: str, flow_splat: bool,
                     pushed_flows: Optional[Tuple[np.ndarray, np.ndarray]] = None,
                     bend: Optional[Bend] = None) -> Tuple[np.ndarray, np.ndarray]:
    """(image [H, W, 3], weight [H, W]): between_target's flow half, the frame at s predicted from
    the pair's flows alone (its arguments)."""

    def backward(item):
        """(W0, W1, ok): the frames sampled backward along estimator h's flows"""
        h, p = item
        if bend is not None:
            g0, g1 = bend.paths(p.flow, p.flow_bw, s, h)
            d0, d1 = -g0, -g1
        else:
            d0, d1 = -s * p.flow, -(1.0 - s) * p.flow_bw
        return _warp_pair(f0, f1, d0, d1)

    # the hypotheses' warps are independent: numpy and OpenCV release the GIL in most of their array
    # work, so the host pool's threads use the cores the device leaves idle meanwhile
    sources = (pair, *extra)
    hyps = list(_host_pool().map(backward, enumerate(sources)))
    if len(hyps) == 1:
        w0, w1, weight = hyps[0]
        image = ((1.0 - s) * w0 + s * w1).astype(np.float32)
    else:
        image, weight = fused_interpolation([(w0, w1) for w0, w1, _ in hyps], s, [ok for _, _, ok in hyps], fuse)
    if flow_splat:
        flow, flow_bw = consistent_flows(sources) if pushed_flows is None else pushed_flows
        g0, g1 = (bend.paths(flow, flow_bw, s) if bend is not None
                  else (np.float32(s) * flow, np.float32(1.0 - s) * flow_bw))
        image = reversed_splat_interpolation(f0, f1, g0, g1, s, image)
    return image, weight


def consistent_flows(sources: Sequence[object]) -> Tuple[np.ndarray, np.ndarray]:
    """(flow, flow_bw) [H, W, 2] each: the flows of sources (FlowPairs of the same two frames from
    several estimators) fused per pixel, each direction weighted by its forward-backward error
    e_h(p) = |F_h(p) + B_h(p + F_h(p))| (bilinear; B_h the estimator's flow the other way) as
    exp(-(e_h - min_h e_h) / PUSH_TAU), normalised.  Where one estimator's flow returns to its
    start and the others' do not, its flow is taken; where they agree, their mean."""
    if len(sources) == 1:
        return np.asarray(sources[0].flow, np.float32), np.asarray(sources[0].flow_bw, np.float32)
    fw = [np.asarray(p.flow, np.float32) for p in sources]
    bw = [np.asarray(p.flow_bw, np.float32) for p in sources]
    out = []
    for there, back in ((fw, bw), (bw, fw)):
        err = np.stack([np.linalg.norm(f + sample_displaced(b, f), axis=-1) for f, b in zip(there, back)])  # [K, H, W]
        wt = np.exp((err.min(0) - err) * np.float32(1.0 / PUSH_TAU))
        wt /= wt.sum(0)
        fused = np.zeros_like(there[0])
        for wk, f in zip(wt, there):
            fused += wk[..., None] * f
        out.append(fused)
    return out[0], out[1]


@functools.lru_cache(maxsize=1)
def _host_pool() -> ThreadPoolExecutor:
    """The threads that build an in-between target's hypotheses, one per core (at most 8)."""
    return ThreadPoolExecutor(max_workers=max(1, min(8, os.cpu_count() or 1)), thread_name_prefix="between")


def _push(item):
    """(frame, g) -> reversed_splat of the frame's image along g, its tool pixels left out."""
    return reversed_splat(item[0].image, item[1], _source_weight(item[0]))


def _source_weight(f) -> Optional[np.ndarray]:
    """[H, W] 1 on tissue, 0 on tool pixels (not splatted), or None without a mask."""
    return None if f.mask is None else (np.asarray(f.mask) > 0.5).astype(np.float32)


def _divide_where(num: np.ndarray, den: np.ndarray, fill: np.ndarray) -> np.ndarray:
    """[H, W, C]: num / den where den ([H, W]) > SPLAT_MIN_WEIGHT, fill elsewhere.  OpenCV's
    per-element division and masked copy (numpy's where= over a broadcast channel axis is several
    times slower); cv2.divide gives 0 where den is 0, and those pixels keep fill."""
    out = np.array(fill, np.float32, copy=True)
    num = np.asarray(num, np.float32)
    den3 = cv2.merge([np.asarray(den, np.float32)] * num.shape[2]) if num.ndim == 3 else den
    cv2.copyTo(cv2.divide(num, den3), (den > SPLAT_MIN_WEIGHT).view(np.uint8), out)
    return out


def reversed_splat(image: np.ndarray, g: np.ndarray, source_weight=None):
    """(pushed [H, W, C], reach [H, W]) of image [H, W, C] pushed forward along g ([H, W, 2]): the
    displacement itself is splatted forward (baselines.splat_forward) and normalised, which gives
    at every pixel q that a source pixel reaches where its colour comes from, q - g; the image is
    sampled there bicubically (SAMPLER: it keeps the texture that a bilinear colour splat averages
    away).  reach: the splatted weight (0 where nothing lands, and pushed is the image sampled at q)."""
    g = np.asarray(g, np.float32)
    num, den = splat_forward(-g, g, source_weight)                                    # [H, W, 2], [H, W]
    back = _divide_where(num, den, np.zeros_like(g))
    return sample_displaced(image, back, SAMPLER), den


def reversed_splat_interpolation(f0, f1, g0: np.ndarray, g1: np.ndarray, s: float, fill: np.ndarray) -> np.ndarray:
    """[H, W, 3]: frames f0 and f1 pushed forward along g0 and g1 ([H, W, 2]: each pixel's
    displacement from its frame to s) to fraction s (reversed_splat, the two on the host pool's
    threads), blended with weights (1 - s) min(reach0, 1) and s min(reach1, 1) where each frame
    reaches the pixel (reach: its splatted weight, above SPLAT_MIN_WEIGHT; a pixel that one frame
    reaches and the other does not, or reaches thinly, comes from the first); fill where that weight
    is not above SPLAT_MIN_WEIGHT.  A frame that splats more than a whole pixel's weight somewhere
    (its motion converges there) counts as one that reaches it once: the frame that stretches there
    is the less certain one, the one that converges is not the more certain (research/QUALITY.md
    finding 52).  Tool pixels (masks) are not pushed."""
    pushed = tuple(_host_pool().map(_push, ((f0, g0), (f1, g1))))
    image = np.zeros(fill.shape, np.float32)
    total = np.zeros(fill.shape[:2], np.float32)
    for a, (w, reach) in ((1.0 - s, pushed[0]), (s, pushed[1])):
        ok = (reach > SPLAT_MIN_WEIGHT).view(np.uint8)                                   # [H, W]
        wt = np.where(ok, np.float32(a) * np.minimum(reach, np.float32(1)), np.float32(0))  # [H, W]
        image += cv2.merge((wt, wt, wt)) * w
        total += wt
    return _divide_where(image, total, fill)


def _warp_pair(f0, f1, d0, d1):
    """(W0, W1 [H, W, 3], ok [H, W]): frames f0 and f1 sampled at p + d0 and p + d1 ([H, W, 2];
    bicubic, SAMPLER); ok 1 where both warped tool masks (bilinear) show tissue, everywhere without
    masks."""
    ok = np.ones(f0.image.shape[:2], np.float32)
    for f, d in ((f0, d0), (f1, d1)):
        if f.mask is not None:
            ok *= (sample_displaced(np.asarray(f.mask, np.float32), d) > 0.5).astype(np.float32)
    return sample_displaced(f0.image, d0, SAMPLER), sample_displaced(f1.image, d1, SAMPLER), ok


def level_fraction(s: float, levels: int) -> float:
    """s in (0, 1) moved onto the grid j / levels, j = 1 .. levels - 1 (between_levels): the grid
    point of the (levels - 1) equal parts of (0, 1) that s falls in; s itself for levels < 2."""
    if levels < 2:
        return s
    j = 1 + min(int(s * (levels - 1)), levels - 2)
    return j / float(levels)


def draw_fraction(rng: np.random.Generator, distribution: str = "uniform") -> float:
    """s in (0, 1) of an in-between step, drawn as distribution says (S_DISTRIBUTIONS)."""
    if distribution == "triangular":
        return 0.5 * (float(rng.uniform(0.0, 1.0)) + float(rng.uniform(0.0, 1.0)))
    return float(rng.uniform(0.0, 1.0))


def pair_time(scene, pair, s: float) -> float:
    """The time at fraction s between the pair's two frames."""
    return (1.0 - s) * float(scene.frames[pair.src].time) + s * float(scene.frames[pair.dst].time)


def targets_on_device(rt) -> bool:
    """Whether in-between targets are built on rt's device (ENV_BETWEEN_TARGET; auto: on a GPU)."""
    where = env.get(ENV_BETWEEN_TARGET, "auto")
    return where == "device" or (where == "auto" and rt.is_gpu)


class BetweenSampler:
    """Draws (camera, time, device targets) of in-between frames for the trainer: a training pair,
    then s in (0, 1) as s_distribution says (draw_fraction).  The pair is drawn uniformly.  extra_flows: {k: FlowPair} of further estimators for the same pairs, fused
    into every target as fuse says (between_target's extra and fuse).  model_splat: the model's
    prediction splats the frames forward (between_target's model_fwd); flow_splat: as
    between_target's, the fused flows it pushes along (consistent_flows) made once per pair.
    motion_refresh > 0: the motion the model renders at a pair's two frames is
    rendered over the whole pair (G0 from the first frame to the second, G1 back) and kept for
    that many steps; the motion to s is s G0 and (1 - s) G1 (the means move linearly in time, so
    up to perspective: a few thousandths of a pixel on the pulling frames, research/QUALITY.md finding
    22).  0: both are rendered to s in every step that needs them.  path (PATHS): "quadratic" bends
    every flow's paths with the pair's Bend (pair_bend, made once per pair)."""

    def __init__(self, rt, scene, flows: Dict[int, object], extra_flows: Sequence[Dict[int, object]] = (),
                 fuse: str = "agree", model_splat: bool = False, flow_splat: bool = False,
                 motion_refresh: int = 0, s_distribution: str = "uniform", path: str = "linear",
                 levels: int = 0, cache_bytes: int = TARGET_CACHE_BYTES):
        self.rt, self.scene, self.fuse = rt, scene, fuse
        self.levels = int(levels)
        # (pair index, grid point j) -> (image [H, W, 3] float16, weight [H, W] float16): the flow
        # prediction at s = j / levels, kept up to cache_bytes (levels >= 2 only)
        self._static: Dict[Tuple[int, int], Tuple[np.ndarray, np.ndarray]] = {}
        self._cache_left = int(cache_bytes)
        self.s_distribution = s_distribution
        self.model_splat, self.flow_splat = model_splat, flow_splat
        self._pushed: Dict[int, Tuple[np.ndarray, np.ndarray]] = {}   # pair index -> consistent_flows
        self.path = path
        self._bends: Dict[int, Optional[Bend]] = {}                      # pair index -> pair_bend
        self.motion_refresh = int(motion_refresh)
        self._motion: Dict[int, Tuple[int, np.ndarray, np.ndarray]] = {}   # pair index -> (step, G0, G1)
        self.pairs = usable_pairs(scene, flows)
        self.extra_flows = list(extra_flows)
        # the target built on the device (train/between_device.py) where a device is given and
        # ENV_BETWEEN_TARGET chooses it; else on the host
        self.device = None
        if rt is not None and self.pairs and targets_on_device(rt):
            self.device = self.device_target()

    def device_target(self):
        """A between_device.DeviceTarget of this sampler on its runtime: the pairs' frames and
        flows uploaded, their fused flows and Bends made."""
        return DeviceTarget(self.rt, self, FUSE_RADIUS, FUSE_TAU, SPLAT_MIN_WEIGHT, pair_bend, SAMPLER)

    def extra(self, pair) -> List[object]:
        """The further estimators' FlowPairs of the pair's two frames."""
        return extra_pairs(self.extra_flows, pair)

    def __bool__(self) -> bool:
        return bool(self.pairs)

    def draw(self, rng: np.random.Generator, model_flow=None, model_weight: float = 0.0, step: int = 0):
        """(camera, time, device targets) of one in-between step, or None where nothing is
        supervised (targets built on the device leave their count there: the step finds it zero
        after its read-back and is dropped then, train.trainer.Trainer._step).
        model_flow(camera, t, t_to) -> [H, W, 2]: the model's rendered displacement from t to t_to,
        blended into the target with model_weight (between_target); it is called first at the
        step's own time, then (model_splat) at the pair's two frames' times, unless their motion
        rendered within motion_refresh steps before ``step`` is kept."""
        index = int(rng.integers(len(self.pairs)))
        pair = self.pairs[index]
        s = level_fraction(draw_fraction(rng, self.s_distribution), self.levels)
        f0, f1 = self.scene.frames[pair.src], self.scene.frames[pair.dst]
        t = pair_time(self.scene, pair, s)
        disp = fwd = None       # fwd: ((motion, factor or None), ...) of the two frames
        if model_flow is not None and model_weight > 0.0:
            disp = model_flow(f0.camera, t, float(f0.time))
            if self.model_splat and self.motion_refresh > 0:
                g0, g1 = self._pair_motion(index, model_flow, step)
                fwd = ((g0, np.float32(s)), (g1, np.float32(1.0 - s)))
            elif self.model_splat:
                fwd = ((model_flow(f0.camera, float(f0.time), t), None), (model_flow(f1.camera, float(f1.time), t), None))
        if self.device is not None:
            image, weight, count = self.device.build(index, s, disp, model_weight, fwd)
            return f0.camera, t, device_targets(self.rt, image, weight, count)   # count: read with the losses
        fwd = None if fwd is None else tuple(g if c is None else c * g for g, c in fwd)
        image, weight, t = self.target(index, s, disp, model_weight, fwd)
        if not weight.any():
            return None
        return f0.camera, t, prepare_targets(self.rt, image, weight, temporary=True)

    def target(self, index: int, s: float, model_disp=None, model_weight: float = 0.0, model_fwd=None):
        """between_target of pair index at fraction s with this sampler's settings: (image [H, W, 3],
        weight [H, W], time).  Without the model's motion (the defaults) it is the static target:
        the pair's flow interpolation alone."""
        pair = self.pairs[index]
        image, weight = self.flow_prediction(index, s)
        image, weight = blend_model_prediction(self.scene, pair, s, image, weight, model_disp, model_weight,
                                               model_fwd)
        return image, weight, pair_time(self.scene, pair, s)

    def flow_prediction(self, index: int, s: float) -> Tuple[np.ndarray, np.ndarray]:
        """(image [H, W, 3], weight [H, W]) float32: the flow prediction of pair index at fraction s
        (between_target without the model).  With levels >= 2 and s on the grid it is made once
        per pair and grid point and kept (float16: within 5e-4 of the float32 result) while the
        cache has room."""
        j = int(round(s * self.levels)) if self.levels >= 2 else 0
        key = (index, j)
        if j and abs(j - s * self.levels) < 1e-6 and key in self._static:
            image, weight = self._static[key]
            return image.astype(np.float32), weight.astype(np.float32)
        pair = self.pairs[index]
        pushed = self._fused(index) if self.flow_splat else None
        bend = None
        if self.path == "quadratic":
            if index not in self._bends:
                self._bends[index] = pair_bend(self.scene, self.pairs, index, lambda p: [p, *self.extra(p)],
                                               self._fused if self.flow_splat else None)
            bend = self._bends[index]
        f0, f1 = self.scene.frames[pair.src], self.scene.frames[pair.dst]
        image, weight = _flow_prediction(f0, f1, pair, s, self.extra(pair), self.fuse, self.flow_splat,
                                         pushed, bend)
        if j and abs(j - s * self.levels) < 1e-6 and self._cache_left >= image.size * 2 + weight.size * 2:
            kept = (image.astype(np.float16), np.asarray(weight).astype(np.float16))
            self._static[key] = kept
            self._cache_left -= kept[0].nbytes + kept[1].nbytes
            return kept[0].astype(np.float32), kept[1].astype(np.float32)   # the same target every time
        return image, weight

    @classmethod
    def from_config(cls, rt, scene, cfg, flows: Dict[int, object],
                    extra_flows: Sequence[Dict[int, object]] = ()) -> "BetweenSampler":
        """The sampler a TrainConfig's between_* keys describe."""
        return cls(rt, scene, flows, extra_flows, cfg.between_fuse, cfg.between_model_splat, cfg.between_flow_splat,
                   cfg.between_motion_refresh, cfg.between_s, cfg.between_path, cfg.between_levels)

    def _fused(self, index: int) -> Tuple[np.ndarray, np.ndarray]:
        """consistent_flows of pair index's estimators, made once."""
        if index not in self._pushed:
            pair = self.pairs[index]
            self._pushed[index] = consistent_flows([pair, *self.extra(pair)])
        return self._pushed[index]

    def kept_motion(self) -> Dict[int, Tuple[int, np.ndarray, np.ndarray]]:
        """The model motion kept per pair (_pair_motion), as a dict the trainer can put back with
        keep_motion: a step done again renders what a skipped one had rendered and kept."""
        return dict(self._motion)

    def keep_motion(self, kept: Dict[int, Tuple[int, np.ndarray, np.ndarray]]) -> None:
        self._motion = dict(kept)

    def _pair_motion(self, index: int, model_flow, step: int) -> Tuple[np.ndarray, np.ndarray]:
        """(G0, G1) [H, W, 2] each: the motion the model renders at pair index's first frame to its
        second and back, rendered again once older than motion_refresh steps."""
        kept = self._motion.get(index)
        if kept is None or step - kept[0] >= self.motion_refresh:
            pair = self.pairs[index]
            f0, f1 = self.scene.frames[pair.src], self.scene.frames[pair.dst]
            t0, t1 = float(f0.time), float(f1.time)
            kept = (step, model_flow(f0.camera, t0, t1), model_flow(f1.camera, t1, t0))
            self._motion[index] = kept
        return kept[1], kept[2]


def between_flows(scene, cfg, progress: bool = False) -> Tuple[Dict[int, object], List[Dict[int, object]]]:
    """(flows, extra_flows): the training pairs' flows of cfg.flow_method and of the between_flows
    estimators ({k: FlowPair} each, cached on disk), as the in-between targets fuse them.  A scene
    that brings its own flow (flow/) has no further estimators: every method reads that flow."""
    own = flow_for_scene(scene, method=cfg.flow_method, progress=progress, max_pixels=cfg.flow_max_pixels)
    extra = []
    for m in between_flow_methods(cfg):
        f = flow_for_scene(scene, method=m, progress=progress, max_pixels=cfg.flow_max_pixels)
        if f.method == "user":
            return dict(own), []
        extra.append(dict(f))
    return dict(own), extra


class Teacher:
    """The in-between teacher as an interpolator with no model (baselines.py "teacher"): the static
    target an in-between step trains on (between_target without the model's motion: the estimators'
    flows fused, pushed forward, reverse-splatted, bicubic, along curved paths), built at a held-out
    frame from the training pair around it exactly as training builds it there.  It uses only the
    training frames.  cfg: the TrainConfig whose between_* and flow keys say how (a baseline fixed
    across runs takes the defaults)."""

    def __init__(self, scene, cfg, progress: bool = False):
        flows, extra = between_flows(scene, cfg, progress)
        self.sampler = BetweenSampler.from_config(None, scene, cfg, flows, extra)
        self.sampler.levels = 0                     # the exact target at any fraction, nothing kept
        self.index = {(p.src, p.dst): i for i, p in enumerate(self.sampler.pairs)}

    def image(self, i0: int, i1: int, s: float) -> Optional[np.ndarray]:
        """[H, W, 3] float32: the target at fraction s between training frames i0 and i1, or None
        where (i0, i1) is not a training pair with one camera (no flow between them)."""
        index = self.index.get((i0, i1))
        if index is None:
            return None
        return np.clip(self.sampler.target(index, s)[0], 0.0, 1.0)

    def motion(self, i0: int, i1: int) -> Optional[float]:
        """The mean magnitude (px) of the flow from training frame i0 to i1 over the pixels where
        it passed its forward-backward check (all pixels where none did), or None where (i0, i1)
        is not a training pair: how far the tissue moves between them."""
        index = self.index.get((i0, i1))
        if index is None:
            return None
        p = self.sampler.pairs[index]
        mag = np.linalg.norm(np.asarray(p.flow, np.float32), axis=-1)
        valid = np.asarray(p.valid) > 0.5 if getattr(p, "valid", None) is not None else None
        return float(mag[valid].mean() if valid is not None and valid.any() else mag.mean())
