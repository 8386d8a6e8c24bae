"""Supervision at times between two training frames, from the training pair's own flow.

A training step renders only at the training frames' times, so nothing says what the model shows
in between: its Gaussians may fit each frame on its own (noise and compression artefacts too) and
blend those fits between frames, which is what the test frames then see (docs/QUALITY.md).  The
pseudo ground-truth flow of every training pair (k, k') is known before training, so the frame at a
time fraction s between them can be predicted, as a flow interpolator does:

    W0(p) = I_k(p - s F_kk'(p)),  W1(p) = I_k'(p - (1 - s) F_k'k(p)),  target = (1 - s) W0 + s W1

(the DIS baseline's warp, ``baselines.dis_interpolations``; the frames are sampled between
pixels as ``between_sampler`` says: bicubically by default, since bilinear sampling at the
half-pixel offsets of a midway warp averages neighbouring pixels and teaches a blurred frame).
Every pixel is supervised, also where the flow failed its forward-backward check: there the target degrades towards a blend of
the two frames, which still bounds what the model may show in between (supervising only the
trusted pixels measured 0.25 dB lower on the pulling frames, docs/QUALITY.md).  With tool masks,
only pixels that show tissue in both warped frames are supervised.  The step uses the colour
losses (L1, D-SSIM, wavelet) and no depth or flow term.  Pairs whose two cameras differ are not
used: an image-space warp predicts nothing for a moving camera.
"""
from __future__ import annotations

from typing import Dict, List, Tuple

import numpy as np

from ..baselines import sample_displaced, two_flow_displacements


def _same_camera(a, b) -> bool:
    return (a.width == b.width and a.height == b.height
            and np.allclose([a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy])
            and np.allclose(np.asarray(a.viewmat, np.float64), np.asarray(b.viewmat, np.float64), atol=1e-6))


def usable_pairs(scene, flows: Dict[int, object]) -> List[object]:
    """The training pairs (data.flow.FlowPair) whose two frames share the camera, in frame order."""
    return [p for k, p in sorted(flows.items()) if _same_camera(scene.frames[p.src].camera, scene.frames[p.dst].camera)]


def between_target(scene, pair, s: float, two_flow: bool = False,
                   sampler: str = "linear") -> Tuple[np.ndarray, np.ndarray, float]:
    """(image [H, W, 3], weight [H, W], time) of the frame at fraction s in (0, 1) between the pair's
    frames (module docstring); weight 1 where the target is supervised, 0 elsewhere.  two_flow:
    where each frame's pixels are taken from comes from both flows (baselines.two_flow_displacements)
    instead of each frame's own.  sampler: how the frames are sampled between pixels
    (baselines.SAMPLERS); the masks are always sampled bilinearly."""
    f0, f1 = scene.frames[pair.src], scene.frames[pair.dst]
    if two_flow:
        d0, d1 = two_flow_displacements(pair.flow, pair.flow_bw, s)              # [H, W, 2] each
    else:
        d0, d1 = -s * pair.flow, -(1.0 - s) * pair.flow_bw
    image = ((1.0 - s) * sample_displaced(f0.image, d0, sampler)
             + s * sample_displaced(f1.image, d1, sampler)).astype(np.float32)
    weight = np.ones(image.shape[:2], np.float32)
    for f, d in ((f0, d0), (f1, d1)):
        if f.mask is not None:
            weight *= (sample_displaced(np.asarray(f.mask, np.float32), d) > 0.5).astype(np.float32)
    t = (1.0 - s) * float(f0.time) + s * float(f1.time)
    return image, weight, t


class BetweenSampler:
    """Draws (camera, time, device targets) of in-between frames for the trainer: a training pair
    uniformly, then s uniformly in (0, 1)."""

    def __init__(self, rt, scene, flows: Dict[int, object], two_flow: bool = False, sampler: str = "linear"):
        self.rt, self.scene, self.two_flow, self.sampler = rt, scene, two_flow, sampler
        self.pairs = usable_pairs(scene, flows)

    def __bool__(self) -> bool:
        return bool(self.pairs)

    def draw(self, rng: np.random.Generator):
        from .device_losses import prepare_targets
        pair = self.pairs[int(rng.integers(len(self.pairs)))]
        s = float(rng.uniform(0.0, 1.0))
        image, weight, t = between_target(self.scene, pair, s, self.two_flow, self.sampler)
        if not weight.any():
            return None
        return self.scene.frames[pair.src].camera, t, prepare_targets(self.rt, image, weight)
