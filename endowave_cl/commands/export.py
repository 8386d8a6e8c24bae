"""Export a trained run's model at time t as a standard 3DGS PLY (opens in common Gaussian viewers),
in the units of the scene's depth files and poses."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from ..checkpoint import load_newest_good_checkpoint
from ..data.scene import load_scene
from ..errors import EndowaveError
from ..export_ply import export_ply
from ..run_io import check_run_scene, run_world_scale


def add_arguments(p) -> None:
    p.add_argument("run", help="run folder written by endowave-cl train")
    p.add_argument("--time", type=float, default=0.0, help="normalised time in [0, 1] (frame i of N is i/(N-1))")
    p.add_argument("--out", help="PLY path (default RUN/model_t<time>.ply)")


def _check_scene(run, state, ck, world_scale) -> None:
    """The run's scene fingerprint against its scene folder, when that folder is still there (the
    PLY is in the units of the scene the run was trained on: another one's would not match it)."""
    try:
        d = json.loads((Path(run) / "config.json").read_text())
        scene_path, downscale = Path(d["scene"]), float(d.get("downscale", 1))
    except (OSError, ValueError, KeyError, TypeError):
        return                       # an older or damaged config.json: nothing to check against
    if not isinstance(state.get("extra", {}).get("scene_fingerprint"), dict):
        return
    if not scene_path.is_dir():
        print(f"note: the run's scene {scene_path} is not there; the PLY is not checked against it", file=sys.stderr)
        return
    check_run_scene(state, load_scene(scene_path, downscale=downscale, world_scale=world_scale), ck,
                    remedy=f"put the run's scene back at {scene_path}, or move it away to export unchecked")


def run(args) -> int:
    if not 0.0 <= args.time <= 1.0:
        raise EndowaveError(f"--time must be in [0, 1], got {args.time}")
    run = Path(args.run)
    if not run.is_dir():
        raise EndowaveError(f"{run}: run folder not found")
    out = Path(args.out) if args.out else run / f"model_t{args.time:.3f}.ply"
    if out.is_dir():
        raise EndowaveError(f"{out}: is a folder; --out names the PLY file to write")
    for parent in out.parents:
        if parent.exists():
            if not parent.is_dir():
                raise EndowaveError(f"{out}: cannot write there: {parent} is a file")
            break
    # the newest checkpoint that reads back (an older one, with a warning, if the newest is corrupt)
    ck, state = load_newest_good_checkpoint(run, log=lambda m: print(m, file=sys.stderr))
    if ck is None:
        raise EndowaveError(f"{args.run}: no checkpoint_*.npz found")
    g = state["gaussians"]
    world_scale = run_world_scale(state, ck)
    _check_scene(run, state, ck, world_scale)
    n = export_ply(out, g, args.time, scale=1.0 / world_scale)   # in the scene files' units
    print(f"wrote {out} ({n if n is not None else '?'} Gaussians at t = {args.time}, in the units of "
          f"the scene's depth files and poses)")
    return 0
