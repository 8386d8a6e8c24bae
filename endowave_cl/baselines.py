"""What a user gets on the test frames without a 4D model (DESIGN.md "Evaluation, the way papers
report it"): two interpolations between the training frames around each test frame.

- ``mean``: the two neighbouring training frames blended by the test frame's time fraction a,
  (1 - a) I0 + a I1.  Every test frame of the EndoNeRF split lies midway (a = 1/2), where this is
  the plain mean of the two frames.
- ``dis``: flow interpolation.  OpenCV DIS flow both ways between the two neighbours
  (``data.flow.estimate_flow``, the estimator and preset the trainer's pseudo ground truth uses),
  each frame backward-warped to the test time and the two blended by the time fraction:
  W0(p) = I0(p - a F01(p)), W1(p) = I1(p - (1 - a) F10(p)), result (1 - a) W0 + a W1.  The flow at
  p in the unseen frame is approximated by the flow at p in each neighbour (the usual half-way
  warp for a = 1/2); samples outside the image repeat the border.  The warps sample bilinearly.
- ``dis_cubic``: the same interpolation with bicubic warps (``SAMPLERS``).  At the half-pixel
  offsets of a midway warp bilinear sampling averages two pixels, a low-pass that costs fine
  texture; bicubic sampling keeps more of it (on the pulling frames at 320x256: LPIPS 0.026 against
  0.039, +0.05 dB; research/QUALITY.md finding 10).  The stronger of the two interpolators is the bar.

- ``teacher``: the in-between teacher (train/between.py ``Teacher``): the target that training's
  in-between steps fit at that time, built from the training pair around the test frame as the
  default settings build it (three flow estimators fused by consistency, the frames pushed forward
  along the fused flows and reverse-splatted, bicubic, along curved paths through the training frames
  beyond the pair), with no model.  It is the strongest interpolator the project builds from the
  training frames alone, so it is the bar a model's unseen times are held to.  Where the neighbours
  are not a training pair with one camera it is ``dis_cubic``'s image.

Neighbours are the nearest training frames before and after the test frame in time; at a sequence
end only one exists, and every baseline is that frame.

``baseline_scores`` scores them on a scene's test frames with ``metrics.frame_scores``, the same
function the model is scored with, and keeps the result in memory per scene (path, size and split),
so repeated evaluations (training-time, several runs in one process) compute it once.
"""
from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np

from .data.flow import estimate_flow
from .errors import EndowaveError
from .metrics import frame_scores
# the warps live in warp.py; these names are read from here too (tools, research, tests)
from .warp import SAMPLERS, sample_displaced, splat_forward, two_flow_displacements, warp_backward  # noqa: F401

NAMES = ("mean", "dis", "dis_cubic", "teacher")
LABELS = {"mean": "neighbour mean", "dis": "DIS flow interpolation",
          "dis_cubic": "DIS flow interpolation, bicubic warps", "teacher": "in-between teacher (no model)"}

# (scene path, width, height, train, test) -> {"lpips": bool, "frames": [per test frame dict]}
_CACHE: Dict[tuple, dict] = {}


def neighbours(scene, k: int) -> Tuple[int, int, float]:
    """(i0, i1, a): the nearest training frames before and after frame k in time and k's time
    fraction between them, a = (t_k - t_i0) / (t_i1 - t_i0).  At a sequence end i0 == i1 (the one
    training frame available) and a = 0."""
    t = scene.frames[k].time
    train = [i for i in scene.train_indices if i != k]
    if not train:
        raise EndowaveError(f"{scene.path}: no training frame to interpolate test frame {k} from")
    before = [i for i in train if scene.frames[i].time <= t]
    after = [i for i in train if scene.frames[i].time >= t]
    i0 = max(before, key=lambda i: scene.frames[i].time) if before else None
    i1 = min(after, key=lambda i: scene.frames[i].time) if after else None
    if i0 is None or i1 is None:
        i = i1 if i0 is None else i0
        return i, i, 0.0
    t0, t1 = scene.frames[i0].time, scene.frames[i1].time
    return i0, i1, (0.0 if t1 == t0 else (t - t0) / (t1 - t0))


def mean_interpolation(image0: np.ndarray, image1: np.ndarray, a: float = 0.5) -> np.ndarray:
    """(1 - a) image0 + a image1: the neighbour mean, weighted by the time fraction a."""
    return ((1.0 - a) * np.asarray(image0, np.float32) + a * np.asarray(image1, np.float32)).astype(np.float32)


def dis_interpolation(image0: np.ndarray, image1: np.ndarray, a: float = 0.5, method: str = "dis",
                      sampler: str = "linear") -> np.ndarray:
    """Flow interpolation at time fraction a between image0 (a = 0) and image1 (a = 1); see the
    module docstring.  [H, W, 3] float RGB in [0, 1] in and out; sampler: SAMPLERS key of the warps."""
    return dis_interpolations(image0, image1, a, method, (sampler,))[sampler]


def dis_interpolations(image0: np.ndarray, image1: np.ndarray, a: float, method: str = "dis",
                       samplers=("linear",)) -> Dict[str, np.ndarray]:
    """{sampler: dis_interpolation(image0, image1, a, method, sampler)} from one pair of flows."""
    if a <= 0.0 or a >= 1.0:
        return {s: np.asarray(image0 if a <= 0.0 else image1, np.float32).copy() for s in samplers}
    f01 = estimate_flow(image0, image1, method)
    f10 = estimate_flow(image1, image0, method)
    return {s: mean_interpolation(sample_displaced(image0, -a * f01, s),
                                  sample_displaced(image1, -(1.0 - a) * f10, s), a) for s in samplers}


def teacher_for(scene, progress: bool = False):
    """The in-between teacher of a loaded scene with the default settings (train/between.py
    Teacher; its flows come from the on-disk flow cache or are estimated once)."""
    # train/ imported here, not at the top: evaluation.py imports this module and stays free of
    # train/ (docs/ARCHITECTURE.md, tests/host/test_gaussians.py)
    from .train.between import Teacher
    from .train.config import TrainConfig
    return Teacher(scene, TrainConfig(), progress)


def baseline_images(scene, k: int, teacher=None) -> Dict[str, np.ndarray]:
    """{name: image} of every baseline (NAMES) for test frame k of a loaded scene.  teacher: the
    scene's teacher_for (made here when None)."""
    i0, i1, a = neighbours(scene, k)
    im0, im1 = scene.frames[i0].image, scene.frames[i1].image
    dis = dis_interpolations(im0, im1, a, samplers=("linear", "cubic"))
    out = {"mean": mean_interpolation(im0, im1, a), "dis": dis["linear"], "dis_cubic": dis["cubic"]}
    taught = None
    if 0.0 < a < 1.0:
        taught = (teacher if teacher is not None else teacher_for(scene)).image(i0, i1, a)
    out["teacher"] = taught if taught is not None else out["dis_cubic"]
    return out


def _key(scene) -> tuple:
    return (str(Path(scene.path).resolve()), scene.width, scene.height, tuple(scene.train_indices),
            tuple(scene.test_indices))


def baseline_scores(scene, with_lpips: bool = False) -> List[dict]:
    """Per test frame (in scene.test_indices order): {"index", "neighbours": [i0, i1], "fraction",
    "motion" (Teacher.motion of the neighbours), and each of NAMES: scores}, scores as metrics.frame_scores gives them.  Cached in memory
    per scene path, size and split; an entry without LPIPS is recomputed when LPIPS is asked for."""
    key = _key(scene)
    hit = _CACHE.get(key)
    if hit is not None and (hit["lpips"] or not with_lpips):
        return hit["frames"]
    rows = []
    teacher = teacher_for(scene)
    for k in scene.test_indices:
        f = scene.frames[k]
        i0, i1, a = neighbours(scene, k)
        row = {"index": k, "neighbours": [i0, i1], "fraction": a, "motion": teacher.motion(i0, i1)}
        for name, img in baseline_images(scene, k, teacher).items():
            row[name] = frame_scores(img, f.image, f.mask, with_lpips)
        rows.append(row)
    _CACHE[key] = {"lpips": with_lpips, "frames": rows}
    return rows


def summarise(rows: List[dict], name: str) -> dict:
    """Mean over the test frames of each figure of one baseline (lpips None when not computed)."""
    out = {}
    for m in ("psnr", "psnr_masked", "ssim", "lpips"):
        vals = [r[name][m] for r in rows]
        out[m] = None if any(v is None for v in vals) else float(np.mean(vals))
    return out
