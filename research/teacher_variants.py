"""The in-between teacher alone (no model) on the validation frames of every shared scene, under
variants of its constants and settings (research/QUALITY.md finding 52).

    python research/teacher_variants.py --variant tau2:PUSH_TAU=2 --variant "more:between_flows=dis,deepflow;PUSH_TAU=2" \
        [--scenes pulling,traction,pushing,synth] [--shared ../shared] [--synth runs/validate/synth_scene]

Each validation frame ((i - 5) % 8 == 0, held out of the training frames) is predicted by the
teacher (train/between.py Teacher: the static target an in-between step trains on, built from the
training pair around the frame as training builds it) and scored as eval scores a model (PSNR over
the tool mask's pixels, LPIPS when its weights are installed).  A variant changes module constants
of train/between.py (PUSH_TAU, FUSE_TAU, FUSE_RADIUS, SPLAT_MIN_WEIGHT; SAMPLER, a warp.SAMPLERS
name) or in-between settings (between_flows, between_fuse, between_flow_splat, between_path),
KEY=VALUE items separated by semicolons; the first column is the defaults.
No test frame is read.  The synthetic scene is the one tools/validate.py makes (skipped when absent).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

SCENES = {"pulling": ("data/endonerf/pulling_soft_tissues", 2.0),
          "traction": ("data/endonerf_clips/traction", 1.0),
          "pushing": ("data/endonerf_clips/pushing", 1.0),
          "synth": (None, 1.0)}
CONSTANTS = ("PUSH_TAU", "FUSE_TAU", "FUSE_RADIUS", "SPLAT_MIN_WEIGHT", "SAMPLER")
KEYS = ("between_flows", "between_fuse", "between_flow_splat", "between_path")


def parse_variant(text: str):
    """'NAME:KEY=VALUE;KEY=VALUE' -> (name, {constant: value}, {setting: text})."""
    name, _, body = text.partition(":")
    consts, keys = {}, {}
    for item in (x.strip() for x in body.split(";") if x.strip()):
        key, _, value = item.partition("=")
        if key in CONSTANTS:
            consts[key] = value
        elif key in KEYS:
            keys[key] = value
        else:
            raise ValueError(f"--variant {text!r}: {key!r} is neither a constant ({', '.join(CONSTANTS)}) "
                             f"nor a setting ({', '.join(KEYS)})")
    if not name:
        raise ValueError(f"--variant {text!r}: expected NAME:KEY=VALUE;...")
    return name, consts, keys


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variant", action="append", default=[], metavar="NAME:KEY=VALUE;...")
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--shared", default="../shared")
    ap.add_argument("--synth", default="runs/validate/synth_scene")
    ap.add_argument("--no-lpips", action="store_true")
    a = ap.parse_args(argv)

    import endowave_cl.train.between as between
    from endowave_cl.baselines import neighbours
    from endowave_cl.data.scene import apply_split, load_scene
    from endowave_cl.errors import EndowaveError
    from endowave_cl.lpips import lpips, lpips_available
    from endowave_cl.metrics import psnr
    from endowave_cl.train.config import TrainConfig, with_values

    try:
        variants = [("defaults", {}, {})] + [parse_variant(v) for v in a.variant]
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    defaults = {c: getattr(between, c) for c in CONSTANTS}
    use_lpips = lpips_available() and not a.no_lpips
    print("teacher on the validation frames: PSNR dB" + (" (LPIPS)" if use_lpips else ""))
    for name in (s.strip() for s in a.scenes.split(",") if s.strip()):
        if name not in SCENES:
            print(f"error: --scenes: unknown scene {name!r} (one of {', '.join(SCENES)})", file=sys.stderr)
            return 2
        rel, downscale = SCENES[name]
        path = Path(a.synth) if rel is None else Path(a.shared) / rel
        if not path.exists():
            print(f"{name}: {path} is absent, skipped")
            continue
        try:
            scene = apply_split(load_scene(path, downscale=downscale), "validation")
        except EndowaveError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2

        def masked(k, img):
            m = scene.frames[k].mask
            return img if m is None else img * m[..., None]

        cells = []
        for vname, consts, keys in variants:
            for c, v in defaults.items():
                setattr(between, c, v)
            for c, v in consts.items():
                setattr(between, c, v if isinstance(defaults[c], str) else type(defaults[c])(float(v)))
            cfg = with_values(TrainConfig(), keys, f"--variant {vname}", from_text=True) if keys else TrainConfig()
            teacher = between.Teacher(scene, cfg)
            scores = []
            for k in scene.test_indices:
                i0, i1, s = neighbours(scene, k)
                image = teacher.image(i0, i1, s) if 0.0 < s < 1.0 else None
                if image is None:
                    continue
                pred, truth = masked(k, image), masked(k, scene.frames[k].image)
                scores.append((psnr(pred, truth), lpips(pred, truth) if use_lpips else np.nan))
            p, l = np.mean(scores, axis=0)
            cells.append(f"{vname} {p:.2f}" + (f" ({l:.4f})" if use_lpips else ""))
        for c, v in defaults.items():
            setattr(between, c, v)
        print(f"{name} ({len(scores)} frames): " + "  ".join(cells), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
