"""Dense torch reference of the whole forward pass (project4d_ref + rasterize_dense_ref).

It does not use the binning, the sort or the tile ranges: each pixel composites every
Gaussian whose tile rectangle holds the pixel's tile, in (depth, index) order.
"""
from __future__ import annotations

from typing import Dict, Optional

from ..camera import Camera
from ..layout import CHANNELS, DEPTH, FLOW, RGB
from .project import project4d_ref
from .rasterize import rasterize_dense_ref


def render_ref(params: Dict[str, "object"], camera: Camera, t: float, t_flow: Optional[float] = None) -> Dict:
    """params: dict of torch tensors in the gaussians.py layout; returns image [H,W,3], depth [H,W],
    flow [H,W,2], alpha [H,W] as torch tensors (differentiable)."""
    p = project4d_ref(params, camera, t, t_flow, channels=CHANNELS)
    out, alpha, _T, _last = rasterize_dense_ref(p["means2d"], p["conic"], p["opac"], p["features"], p["depth"],
                                                p["rect"], camera.width, camera.height)
    return {"image": out[..., RGB], "depth": out[..., DEPTH], "flow": out[..., FLOW], "alpha": alpha}
