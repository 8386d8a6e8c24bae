"""Open a training run folder: its config, its newest checkpoint and its scene."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

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
    from .data.scene import load_scene
    from .train.checkpoint import latest_checkpoint, load_checkpoint
    from .train.config import TrainConfig
    run = Path(run_dir)
    cfg_file = run / "config.json"
    if not cfg_file.is_file():
        raise EndowaveError(f"{run}: not a training run (no config.json); train one with endowave-cl train")
    try:
        d = json.loads(cfg_file.read_text())
    except json.JSONDecodeError as e:
        raise EndowaveError(f"{cfg_file}: not valid JSON: {e}") from None
    scene_path = scene_override or d.pop("scene", None)
    d.pop("scene", None)
    cfg = TrainConfig.from_dict(d, str(cfg_file))
    ck = latest_checkpoint(run)
    if ck is None:
        raise EndowaveError(f"{run}: no checkpoint_*.npz yet")
    state = load_checkpoint(ck)
    scene = load_scene(scene_path, downscale=cfg.downscale)
    return LoadedRun(run, cfg, scene, state["gaussians"], int(state["step"]), ck)


def write_png_atomic(path, image: np.ndarray) -> None:
    """image: [H, W, 3] float RGB in [0, 1], or [H, W] uint8/uint16; written atomically."""
    from .data.atomic import save_png
    if image.dtype in (np.uint8, np.uint16):
        arr = image
    else:
        arr = (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)
    save_png(path, arr[..., ::-1] if arr.ndim == 3 else arr)  # RGB -> BGR for OpenCV
