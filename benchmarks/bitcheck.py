"""The byte-for-byte check a restructuring is held to: N training steps and a render, hashed.

Trains pulling at a reduced size for a few steps with a schedule squeezed so that every kind of
step runs (plain and in-between steps, densification, the model's part of the in-between target
after densify_until), then renders a test frame, and prints SHA-256 prefixes of the parameters
and of the render. Run it before and after a change that must not move results; the two outputs
must be equal on the same machine and device.

    python benchmarks/bitcheck.py [--shared ../shared] [--steps 40]
"""
from __future__ import annotations

import argparse
import hashlib
import sys
import tempfile
from pathlib import Path

import numpy as np

import endowave_cl
from endowave_cl.data.scene import load_scene
from endowave_cl.gaussians import download
from endowave_cl.render import render
from endowave_cl.runtime import get_runtime
from endowave_cl.train.config import TrainConfig, with_values
from endowave_cl.train.trainer import Trainer


def _h(*arrays) -> str:
    d = hashlib.sha256()
    for a in arrays:
        d.update(np.ascontiguousarray(a).tobytes())
    return d.hexdigest()[:16]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shared", default="../shared", help="the shared folder (default ../shared)")
    ap.add_argument("--steps", type=int, default=40)
    a = ap.parse_args(argv)
    src = Path(a.shared) / "data" / "endonerf" / "pulling_soft_tissues"
    if not src.is_dir():
        print(f"bitcheck: {src}: no such scene folder (pass --shared)", file=sys.stderr)
        return 2
    n = a.steps
    cfg = with_values(TrainConfig(), dict(
        iterations=n, downscale=4, init_points=4000, densify_from=n // 4, densify_every=n // 8,
        densify_until=n // 2, between_motion_refresh=n // 8, log_every=10, eval_every=0,
        checkpoint_every=0, seed=0), "bitcheck")
    rt = get_runtime()
    scene = load_scene(src, downscale=cfg.downscale)
    with tempfile.TemporaryDirectory() as tmp:
        tr = Trainer(scene, cfg, Path(tmp) / "run", rt, log=lambda s: None)
        tr.train(progress=False)
        g = download(tr.params)
        k = scene.test_indices[0]
        out = render(rt, tr.params, scene.frames[k].camera, scene.frames[k].time)
        img = out.features.get()                  # [H, W, C]
    print(f"endowave_cl {getattr(endowave_cl, '__version__', '?')} on {getattr(rt, 'name', rt)}")
    print(f"gaussians {len(g)}")
    print(f"params   {_h(g.means, g.scales, g.quat_l, g.quat_r, g.opacity, g.sh, g.phase)}")
    print(f"render   {_h(np.asarray(img))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
