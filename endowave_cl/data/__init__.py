"""Scenes in the EndoNeRF layout: loading, synthetic generation, pseudo ground-truth optical flow.

Public API::

    load_scene(path, downscale=1, depth_percentiles=(3.0, 99.8), hwf_layout="auto",
               use_depth=True, use_masks=True) -> Scene
    make_synthetic_scene(out, width=160, height=128, frames=24, seed=0, deformation=1.0,
                         force=False) -> Path
    flow_for_scene(scene, method="dis", cache=True, progress=True, cache_dir=None,
                   use_user_flow=True) -> SceneFlow ({k: FlowPair})
    read_flow_file(path) -> [H, W, 2]   (.flo or .npy);  write_flo(path, flow)

See docs/DATA.md for the layout and conventions.
"""
from .flo import read_flo, read_flow_file, write_flo
from .flow import METHODS, FlowPair, SceneFlow, estimate_flow, flow_for_scene, training_pairs, valid_mask
from .scene import Frame, Scene, load_scene, split_indices
from .synth import make_synthetic_scene

__all__ = ["Frame", "Scene", "load_scene", "split_indices", "make_synthetic_scene", "METHODS",
           "FlowPair", "SceneFlow", "estimate_flow", "flow_for_scene", "training_pairs",
           "valid_mask", "read_flo", "read_flow_file", "write_flo"]
