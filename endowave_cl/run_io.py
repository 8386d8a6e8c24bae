"""Open a training run folder: its config, its newest checkpoint and its scene."""
from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

from .atomic import write_png_atomic  # noqa: F401  (moved to atomic.py; re-exported for older callers)
from .checkpoint import load_newest_good_checkpoint
from .data.scene import apply_split, load_scene
from .errors import EndowaveError


@dataclass
class LoadedRun:
    path: Path
    cfg: object          # TrainConfig
    scene: object        # data.scene.Scene
    gaussians: object    # Gaussians
    step: int
    checkpoint: Path


def load_run(run_dir, scene_override=None) -> LoadedRun:
    # train/ imported here, not at the top: export, eval and the viewer import this module and
    # stay free of train/ (docs/ARCHITECTURE.md, tests/host/test_gaussians.py)
    from .train.config import TrainConfig, drop_removed
    run = Path(run_dir)
    cfg_file = run / "config.json"
    if not cfg_file.is_file():
        raise EndowaveError(f"{run}: not a training run (no config.json); train one with endowave-cl train")
    try:
        d = json.loads(cfg_file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise EndowaveError(f"{cfg_file}: not valid JSON: {e}") from None
    except OSError as e:
        raise EndowaveError(f"{cfg_file}: cannot read ({e.strerror or e})") from None
    if not isinstance(d, dict):
        raise EndowaveError(f"{cfg_file}: expected a JSON object")
    scene_path = scene_override or d.pop("scene", None)
    d.pop("scene", None)
    if not isinstance(scene_path, str):
        raise EndowaveError(f"{cfg_file}: no scene path recorded; pass --scene")
    # keys of earlier versions (config.py REMOVED) are ignored, so that an old run still opens
    d = drop_removed(d, str(cfg_file), note=lambda m: print(m, file=sys.stderr))
    cfg = TrainConfig.from_dict(d, str(cfg_file))
    # the newest checkpoint that reads back (an older one, with a warning, if the newest is corrupt)
    ck, state = load_newest_good_checkpoint(run, log=lambda m: print(m, file=sys.stderr))
    if ck is None:
        raise EndowaveError(f"{run}: no checkpoint_*.npz yet")
    # in the units the run was trained in (runs from before scene units: the files' own)
    scene = apply_split(load_scene(scene_path, downscale=cfg.downscale, world_scale=run_world_scale(state, ck)),
                        cfg.split)
    check_run_scene(state, scene, ck)
    return LoadedRun(run, cfg, scene, state["gaussians"], int(state["step"]), ck)


def check_run_scene(state, scene, ck, remedy: str = "pass the run's own scene with --scene, or train a run on "
                                                   "this one") -> None:
    """Refuse a scene whose frames are not the ones the run was trained on (--scene OTHER, or the
    scene folder regenerated in place): scores, renders and PLYs against them would be wrong."""
    from .train.run_folder import check_same_scene    # as in load_run: not at the top
    check_same_scene(state.get("extra", {}), scene, ck,
                     remedy=f"evaluating, rendering or exporting against it would be wrong; {remedy}")


def run_world_scale(state, where) -> float:
    """The scene units a checkpoint was trained in (data/scene.py world_scale); 1.0 before they existed."""
    raw = state.get("extra", {}).get("world_scale", 1.0)
    try:
        v = float(raw)
    except (TypeError, ValueError):
        v = math.nan
    if not (math.isfinite(v) and v > 0):
        raise EndowaveError(f"{where}: world_scale {raw!r} is not a positive number")
    return v
