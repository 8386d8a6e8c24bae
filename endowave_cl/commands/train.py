"""Train an EndoWave model on a scene (EndoNeRF layout) or on the built-in synthetic demo scene.

Examples:
  endowave-cl train --demo --out runs/demo
  endowave-cl train scenes/pulling_soft_tissues --out runs/pulling --downscale 2
  endowave-cl train SCENE --out RUN --no-flow --no-wavelet      # the ablation switches
A run folder holds config.json, checkpoints (checkpoint_*.npz: the two newest and the best) and
train_log.json; training an existing run folder resumes from its newest readable checkpoint
(--restart starts over and moves the earlier run's files to RUN/previous_run/).  One train at a
time per run folder (RUN/.lock).  SIGINT / SIGTERM save a checkpoint and stop; a run whose
parameters turn NaN, run away or whose training PSNR collapses stops with an error (exit 1), and the
checkpoints it kept are from before.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import warnings
from pathlib import Path

import cv2
from tqdm import tqdm

from ..data.images import list_images
from ..data.ingest import ingest
from ..data.scene import apply_split, check_supervised, load_scene
from ..data.synth import make_synthetic_scene
from ..errors import EndowaveError
from ..evaluation import flow_references
from ..runtime import get_runtime
from ..train.config import (BASE_ITERATIONS, RECIPES, STEPS_PER_TRAINING_FRAME, load_config, settings_text,
                            validate_config)
from ..train.trainer import Trainer
from .ingest import report

DEMO_SIZE = (160, 128, 24)       # width, height, frames of the built-in demo scene
DEMO_ITERATIONS = 1500           # enough for a clear PSNR rise in a couple of minutes on 2 CPU cores
DEMO_INIT_POINTS = 6000          # ~0.3 Gaussians per pixel at 160x128 (30000 suits 640x512)
DEMO_MAX_GAUSSIANS = 40000       # densification cap for the demo (~2 per pixel), keeps it quick


class _ListSettings(argparse.Action):
    """--list-settings: print the settings table and exit before the other arguments are checked
    (as --help does: no --out needed)."""

    def __init__(self, option_strings, dest, **kw):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kw)

    def __call__(self, parser, namespace, values, option_string=None):
        sys.stdout.write(settings_text())
        parser.exit(0)


def add_arguments(p) -> None:
    p.add_argument("scene", nargs="?", help="scene folder in the EndoNeRF layout, or a video file (ingested into "
                                            "RUN/scene with `endowave-cl ingest`'s defaults; omit with --demo)")
    p.add_argument("--out", required=True, help="run folder (created; an existing one is resumed)")
    p.add_argument("--demo", action="store_true", help="train on the built-in synthetic scene (generated into RUN/demo_scene)")
    p.add_argument("--recipe", choices=tuple(RECIPES),
                   help="the settings to start from: 'default' (this version's), or 'paper' (EndoWave as published: "
                        "30000 steps, 3DGS/4DGS schedule, SH degree 3, opacity reset, no in-between steps); "
                        "--config and --set apply on top")
    p.add_argument("--config", help="TOML file of training settings, KEY = VALUE lines (the keys: --list-settings)")
    p.add_argument("--list-settings", action=_ListSettings,
                   help="print every training setting with its default, range and meaning, and exit")
    p.add_argument("--iterations", type=int,
                   help=f"number of training steps (default: {STEPS_PER_TRAINING_FRAME} per training frame, at "
                        f"least {BASE_ITERATIONS}, with the densification schedule stretched alike)")
    p.add_argument("--minutes", type=float,
                   help="time budget: plan the steps, densification and learning-rate decay to end "
                        "training within this many minutes on this device (prints the plan)")
    p.add_argument("--downscale", type=float, help="image downscale factor (2 = half size)")
    p.add_argument("--validation", action="store_true",
                   help="hold out the validation frames ((i - 5) %% 8 == 0) as well and score those instead of "
                        "the test frames: for choosing settings without reading a test frame")
    p.add_argument("--no-flow", action="store_true", help="turn the optical-flow loss off")
    p.add_argument("--no-wavelet", action="store_true", help="turn the rational-wavelet loss off")
    p.add_argument("--no-depth", action="store_true", help="turn the depth loss off")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override any config key, e.g. --set lambda_flow=0.05 (repeatable; the keys: --list-settings)")
    p.add_argument("--restart", action="store_true",
                   help="start over; the earlier run's files move to RUN/previous_run/")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def build_config(args):
    overrides = {}
    for item in args.set:
        if "=" not in item:
            raise EndowaveError(f"--set expects KEY=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        overrides[k.strip()] = v.strip()
    cfg = load_config(args.config, overrides, getattr(args, "recipe", None))
    changes = {}    # what the options say, over the file and --set (the config is frozen: one replace)
    if args.iterations is not None:
        if args.iterations < 1:
            raise EndowaveError(f"--iterations must be at least 1, got {args.iterations}")
        changes["iterations"] = args.iterations
    elif args.demo and not args.config and "iterations" not in overrides:
        changes["iterations"] = DEMO_ITERATIONS
    if args.demo and not args.config:
        if "init_points" not in overrides:
            changes["init_points"] = DEMO_INIT_POINTS
        if "max_gaussians" not in overrides:
            changes["max_gaussians"] = DEMO_MAX_GAUSSIANS
    if args.downscale is not None:
        check_downscale_arg(args.downscale)
        changes["downscale"] = args.downscale
    if getattr(args, "minutes", None) is not None:
        if not args.minutes > 0:
            raise EndowaveError(f"--minutes must be > 0, got {args.minutes}")
        changes["minutes"] = args.minutes
    if getattr(args, "validation", False):
        changes["split"] = "validation"
    changes["use_flow"] = cfg.use_flow and not args.no_flow
    changes["use_wavelet"] = cfg.use_wavelet and not args.no_wavelet
    changes["use_depth"] = cfg.use_depth and not args.no_depth
    cfg = cfg.replace(**changes)
    validate_config(cfg, "the command line")
    return cfg


MIN_IMAGE_SIZE = 16   # pixels per side after --downscale: the flow estimator and the SSIM window need room


def check_downscale_arg(downscale: float) -> None:
    if not (math.isfinite(downscale) and downscale >= 1):
        raise EndowaveError(f"--downscale must be a finite number >= 1, got {downscale}")


def check_downscaled_size(scene_path, downscale: float) -> None:
    """Refuse a downscale that leaves too few pixels, before the scene loader or OpenCV fail on it."""
    img_dir = Path(scene_path) / "images"
    if downscale == 1 or not img_dir.is_dir():
        return                       # the scene loader reports a missing folder
    files = list_images(img_dir)
    img = cv2.imread(str(files[0]), cv2.IMREAD_UNCHANGED) if files else None
    if img is None:
        return                       # the scene loader names the unreadable file
    h, w = img.shape[:2]
    w2, h2 = int(round(w / downscale)), int(round(h / downscale))
    if min(w2, h2) < MIN_IMAGE_SIZE:
        raise EndowaveError(f"downscale {downscale:g} leaves {w2}x{h2} pixels of the {w}x{h} images in "
                            f"{img_dir} (at least {MIN_IMAGE_SIZE} per side needed)")


def build_notice(rt):
    """The line printed before the first kernel build from source (an empty cache: the first run on
    this device, or after an update), so that a cold start does not look hung."""
    def notice(what: str) -> None:
        how_long = "a few seconds to a minute on a GPU" if rt.is_gpu else "1-2 minutes on a 2-core CPU"
        tqdm.write(f"building the OpenCL kernels for this device (first run here with this version; about "
                   f"{how_long}; cached for later runs; starting with {what}) ...")
    return notice


VIDEO_SCENE = "scene"    # RUN/scene: where `train VIDEO` ingests the video


def ingest_video_into_run(video: Path, out: Path, quiet: bool = False) -> Path:
    """RUN/scene ingested from ``video`` with ingest's defaults, or the one an earlier `train VIDEO`
    made from the same file (a resume)."""
    scene = out / VIDEO_SCENE
    if (scene / "poses_bounds.npy").is_file():
        try:
            src = json.loads((scene / "scene.json").read_text())["ingest"]["source"]
        except (OSError, ValueError, KeyError, TypeError):
            src = None
        if src is not None and Path(src) == video.resolve():
            print(f"using {scene}, ingested from {video} earlier")
            return scene
        raise EndowaveError(f"{scene}: holds a scene made from {src or 'another source'}, not {video} "
                            f"(use another --out, or give that scene folder)")
    print(f"{video}: a video; ingesting it into {scene} (defaults of `endowave-cl ingest`; run that "
          f"command for a frame range, size, intrinsics, masks or stereo depth)")
    report(ingest(video, scene, progress=not quiet))
    return scene


def run(args) -> int:
    # numpy overflows in densification only on parameters that have already diverged; the divergence
    # guard reports that in one line, so its warnings would only be noise
    warnings.filterwarnings("ignore", message="overflow encountered", category=RuntimeWarning)
    if args.demo == bool(args.scene):
        raise EndowaveError("give a SCENE folder or --demo (not both)")
    cfg = build_config(args)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise EndowaveError(f"{out}: exists and is not a folder (--out must be a run folder)")
    scene_path = Path(args.scene) if args.scene else out / "demo_scene"
    if args.scene and scene_path.is_file():          # a video: ingest it into the run folder first
        scene_path = ingest_video_into_run(scene_path, out, quiet=args.quiet)
    if args.demo and not (scene_path / "poses_bounds.npy").is_file():
        w, h, n = DEMO_SIZE
        print(f"generating the demo scene ({w}x{h}, {n} frames) in {scene_path}")
        make_synthetic_scene(scene_path, width=w, height=h, frames=n, seed=0, force=True)
    # load and check everything before touching the run folder
    check_downscaled_size(scene_path, cfg.downscale)
    scene = apply_split(load_scene(scene_path, downscale=cfg.downscale, use_depth=cfg.use_depth), cfg.split)
    print(f"scene {scene_path}: {scene.summary()}")
    if not scene.test_indices or not scene.train_indices:
        raise EndowaveError(f"{scene_path}: {len(scene.frames)} frame(s) give {len(scene.train_indices)} "
                            f"training and {len(scene.test_indices)} test frames; training needs at least "
                            f"one of each (at least 2 frames: frame 1 is the first test frame)")
    check_supervised(scene, scene.split)      # masks leave something to train on and to score (issue 57)
    flow_references(scene)   # gt_flow/ read and checked now, not after training (issue 57); kept for the end
    if not scene.has_depth:
        cfg = cfg.replace(use_depth=False)
    rt = get_runtime(getattr(args, "device", None))
    print(f"device: {rt.describe()}")
    rt.build_notice = build_notice(rt)
    losses = ["rgb"] + [n for n, on in (("depth", cfg.use_depth), ("flow", cfg.use_flow),
                                         ("wavelet", cfg.use_wavelet)) if on]
    auto_sh = cfg.sh_degree < 0          # resolved by the trainer from the cameras (train/config.py)
    trainer = Trainer(scene, cfg, out, rt, resume=not args.restart, progress=not args.quiet)
    cfg = trainer.cfg                    # resolved (steps, density, SH degree) for this scene
    if cfg.minutes > 0:
        plan = f"a {cfg.minutes:g}-minute budget"
    elif trainer.auto_iterations:
        plan = (f"{cfg.iterations} steps (about {cfg.iterations // len(scene.train_indices)} per training "
                f"frame; --minutes plans from a time budget)")
    else:
        plan = f"{cfg.iterations} steps"
    why = ""   # why -1 became this degree; a resumed run has its checkpoint's degree instead
    if auto_sh and trainer.step == 0:
        why = " (one camera centre)" if scene.one_viewpoint() else " (moving cameras)"
    print(f"training {plan}, losses: {', '.join(losses)}; {len(trainer.params['means'])} Gaussians "
          f"(density control up to {cfg.max_gaussians}, gradient threshold {cfg.densify_grad_threshold:.3g}), "
          f"colour SH degree {cfg.sh_degree}{why}")
    m = trainer.train(progress=not args.quiet)
    print(f"final {scene.split} PSNR {m['psnr']:.2f} dB (masked {m['psnr_masked']:.2f} dB), SSIM {m['ssim']:.4f}, "
          f"{m['gaussians']} Gaussians, {m['step']} steps in {m['train_seconds']:.0f} s"
          + (f" (+ {m['build_seconds']:.0f} s building kernels)" if m.get("build_seconds", 0) >= 1 else "")
          + f"; run saved in {out}")
    return 0
