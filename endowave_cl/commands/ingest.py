"""Turn a video file (any format OpenCV reads) or a folder of frames into a scene in the EndoNeRF
layout that `endowave-cl train` reads: images/, poses_bounds.npy (identity poses: a fixed
endoscope), scene.json, and optionally masks/ and depth/.

Examples:
  endowave-cl ingest clip.mp4 scenes/clip --width 320 --stride 2
  endowave-cl ingest frames/ scenes/clip --fov 70 --masks tool_masks/
  endowave-cl ingest stereo.mp4 scenes/st --stereo side-by-side --baseline 4.2   # depth in mm
Intrinsics: --focal (pixels of the source frame) or --fov (horizontal degrees); without either a
60 degree field of view is assumed, and the command warns that it is a guess.  --stereo splits each
frame into the left and right eye, keeps the left one and computes depth with OpenCV's semi-global
matching; the recording must be rectified (rows aligned), nothing here calibrates it.  Masks and
depth folders hold one file per taken frame or one per source frame (in name order), at the source
or the output size.  OUT appears complete or not at all.
"""
from __future__ import annotations

import time

from ..data.ingest import IngestOptions, describe_split, ingest
from ..data.scene import load_scene


def add_arguments(p) -> None:
    p.add_argument("source", help="a video file, or a folder of .png / .jpg frames (name order)")
    p.add_argument("out", help="scene folder to write (must be absent or empty unless --force)")
    p.add_argument("--start", type=int, default=0, help="first source frame to take (0-based; default 0)")
    p.add_argument("--end", type=int, help="source frame to stop before (default: the last)")
    p.add_argument("--stride", type=int, default=1, help="take every N-th frame (default 1)")
    p.add_argument("--max-frames", type=int, help="take at most this many frames")
    p.add_argument("--width", type=int, help="output width in pixels (alone: the height keeps the aspect ratio)")
    p.add_argument("--height", type=int, help="output height in pixels (alone: the width keeps the aspect ratio)")
    p.add_argument("--focal", type=float, help="focal length in pixels of the source frame (one eye's for stereo)")
    p.add_argument("--fov", type=float, help="horizontal field of view in degrees (default: a guessed 60)")
    p.add_argument("--near", type=float, help="near depth bound (default: from the depth, else 1)")
    p.add_argument("--far", type=float, help="far depth bound (default: from the depth, else 100)")
    p.add_argument("--masks", metavar="DIR", help="folder of tool masks (255 = tool) to check and copy")
    p.add_argument("--depth", metavar="DIR", help="folder of 8/16-bit depth maps to check and copy")
    p.add_argument("--depth-scale", type=float, help="units per count of the --depth files (default: the raw values)")
    p.add_argument("--stereo", choices=("side-by-side", "top-bottom"),
                   help="the frames hold a rectified stereo pair, left eye first; depth by semi-global matching")
    p.add_argument("--baseline", type=float, help="stereo baseline; depth comes out in its units (needs --stereo)")
    p.add_argument("--max-disparity", type=int,
                   help="stereo search range in output pixels, a multiple of 16 (default: a quarter of the width)")
    p.add_argument("--force", action="store_true", help="replace a non-empty OUT")
    p.add_argument("--quiet", action="store_true", help="no progress line")


def options_from_args(args):
    return IngestOptions(start=args.start, end=args.end, stride=args.stride, max_frames=args.max_frames,
                         width=args.width, height=args.height, focal=args.focal, fov=args.fov,
                         near=args.near, far=args.far, masks=args.masks, depth=args.depth,
                         depth_scale=args.depth_scale, stereo=args.stereo, baseline=args.baseline,
                         max_disparity=args.max_disparity)


def report(r, log=print) -> None:
    for w in r.warnings:
        log(f"warning: {w}")
    extra = [x for x, on in (("depth", r.has_depth), ("masks", r.has_masks)) if on]
    log(f"{r.out}: {r.frames} frames, {r.width}x{r.height}, f = {r.focal:.1f} px ({r.focal_source})"
        f"{', with ' + ' and '.join(extra) if extra else ', no depth, no masks'}; "
        f"training will use {describe_split(r.train, r.test)}")


def run(args) -> int:
    t0 = time.perf_counter()
    r = ingest(args.source, args.out, options_from_args(args), force=args.force, progress=not args.quiet)
    report(r)
    load_scene(r.out)     # the loader reads what was written (a last check)
    print(f"ingested in {time.perf_counter() - t0:.1f} s; next: endowave-cl train {r.out} --out RUN")
    return 0
