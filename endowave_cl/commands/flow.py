"""Precompute pseudo ground-truth optical flow for a scene (EndoNeRF layout).

Flow between consecutive training frames, both directions, with a forward-backward consistency
mask (tool pixels excluded when the scene has masks), computed with OpenCV (by default the
training's flow_method, DIS fine; DIS is 4x faster, Farneback, DeepFlow and TV-L1 are slower; the
config key between_flows fuses several for the in-between targets) and cached outside the scene
(--cache-dir, else $ENDOWAVE_CL_CACHE/flow, else ~/.cache/endowave-cl/flow); training reuses the
cache while the frames are unchanged.  If SCENE/flow/ holds user flow (.npy / .flo, see
docs/DATA.md), it is checked and used instead.  For a synthetic scene (gt_flow/) the end-point
error against the ground truth is printed.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..data import flow_for_scene, load_scene
from ..data.flo import read_flow_file
from ..data.flow import METHODS, MIN_ESTIMATION_PIXELS, _fit_to_scene
from ..errors import DataError, EndowaveError
from ..train.config import TrainConfig
from .train import check_downscale_arg, check_downscaled_size


def add_arguments(parser):
    default = TrainConfig().flow_method
    parser.add_argument("scene", help="scene folder in the EndoNeRF layout")
    parser.add_argument("--method", choices=METHODS, default=default,
                        help=f"flow estimator (default {default}, the training's flow_method)")
    parser.add_argument("--downscale", type=float, default=1.0,
                        help="image downscale factor, as used for training (default 1)")
    parser.add_argument("--max-pixels", type=int, default=TrainConfig().flow_max_pixels,
                        help="estimate on frames area-averaged to at most this many pixels and scale the "
                             "flow back up (default: the training's flow_max_pixels; 0: the frame's size)")
    parser.add_argument("--cache-dir", default=None, help="cache root (default ~/.cache/endowave-cl/flow)")
    parser.add_argument("--no-cache", action="store_true", help="compute without reading or writing the cache")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def gt_epe(scene, result):
    """Mean end-point error on valid pixels against scene/gt_flow (consecutive pairs only), or None."""
    gt_dir = Path(scene.path) / "gt_flow"
    errs = []
    for k, pair in result.items():
        f = gt_dir / f"{scene.frames[k].name}.npy"
        if pair.dst != k + 1 or not f.is_file() or scene.downscale != 1:
            continue
        valid = pair.valid > 0
        if valid.any():
            # one-line errors naming the file for a damaged one, NaN or absurd vectors (1e30)
            gt = _fit_to_scene(read_flow_file(f), f, scene)
            if gt.shape != pair.flow.shape:
                raise DataError(f"{f}: ground-truth flow is {list(gt.shape)}, the frames are {list(pair.flow.shape)}")
            errs.append(float(np.linalg.norm(pair.flow - gt, axis=-1)[valid].mean()))
    return (float(np.mean(errs)), len(errs)) if errs else None


def run(args) -> int:
    check_downscale_arg(args.downscale)
    check_downscaled_size(args.scene, args.downscale)
    if args.max_pixels < 0 or 0 < args.max_pixels < MIN_ESTIMATION_PIXELS:
        raise EndowaveError(f"--max-pixels must be 0 (the frame's size) or at least {MIN_ESTIMATION_PIXELS}, "
                            f"got {args.max_pixels}")
    scene = load_scene(args.scene, downscale=args.downscale)
    print(f"{args.scene}: {scene.summary()}")
    start = time.perf_counter()
    result = flow_for_scene(scene, method=args.method, cache=not args.no_cache,
                            progress=not args.no_progress, cache_dir=args.cache_dir,
                            max_pixels=args.max_pixels)
    took = time.perf_counter() - start
    valid = np.mean([p.valid.mean() for p in result.values()]) if result else 0.0
    how = "computed" if result.computed else ("read" if result.method == "user" else "reused from cache")
    where = f"; cache {result.cache_path}" if result.cache_path is not None else ""
    print(f"{len(result)} pairs ({result.method}), {how} in {took:.1f} s, "
          f"valid {100 * valid:.1f}% of pixels{where}")
    epe = gt_epe(scene, result)
    if epe is not None:
        print(f"end-point error vs gt_flow on valid pixels: {epe[0]:.3f} px ({epe[1]} pairs)")
    return 0
