"""Generate a synthetic endoscopic scene in the EndoNeRF layout, with ground truth.

A deforming tissue surface with a vessel-like texture, lit by a light at the camera (Blinn-Phong
specular highlights), and a moving surgical tool that occludes it, seen by a static camera.
Writes images/, depth/ (uint16, scale in scene.json), masks/ (255 = tool), poses_bounds.npy,
scene.json, and the ground truth gt_flow/ (forward flow to the next frame) and gt_points/
(camera-space points).  The defaults (160x128, 24 frames) are the built-in demo.
"""
from __future__ import annotations

import time

from ..data.scene import load_scene
from ..data.synth import make_synthetic_scene
from ..errors import DataError


def add_arguments(parser):
    parser.add_argument("out", help="output scene folder (must be absent or empty unless --force)")
    parser.add_argument("--width", type=int, default=160, help="image width in pixels (default 160)")
    parser.add_argument("--height", type=int, default=128, help="image height in pixels (default 128)")
    parser.add_argument("--frames", type=int, default=24, help="number of frames (default 24)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--deformation", type=float, default=1.0,
                        help="amount of tissue deformation, 0 = rigid (default 1.0)")
    parser.add_argument("--force", action="store_true", help="replace a non-empty OUT")


def run(args) -> int:
    start = time.perf_counter()
    try:
        out = make_synthetic_scene(args.out, width=args.width, height=args.height, frames=args.frames,
                                   seed=args.seed, deformation=args.deformation, force=args.force)
    except ValueError as e:    # a parameter out of range: the message names the option, not the folder
        raise DataError(f"{e}") from None
    scene = load_scene(out)
    print(f"{out}: {scene.summary()} ({time.perf_counter() - start:.1f} s)")
    return 0
