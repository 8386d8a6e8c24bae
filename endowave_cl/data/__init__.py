"""Scenes in the EndoNeRF layout: loading, synthetic generation, pseudo ground-truth optical flow.

Public API::

    load_scene(path, downscale=1, depth_percentiles=(3.0, 99.8), hwf_layout="auto", ...) -> Scene
    make_synthetic_scene(out, width=160, height=128, frames=24, seed=0, deformation=1.0, force=False) -> Path
    flow_for_scene(scene, method="dis", cache=True, progress=True, cache_dir=None) -> {k: FlowPair}

See docs/DATA.md for the layout and conventions.
"""
from .scene import Frame, Scene, load_scene, split_indices

__all__ = ["Frame", "Scene", "load_scene", "split_indices"]
