"""Layout constants shared by the host ops, the references and the kernels (torch-free).

One definition of each: the ops pass them to the kernels as build options where the kernels take
them (ALPHA_MAX, ALPHA_MIN, T_STOP, CHANNELS), the references read them from here.

    TILE                     pixels per tile side (TILE in cl/common.h)
    tile_grid(w, h)          (tiles_x, tiles_y) covering a w x h image
    ALPHA_MAX / ALPHA_MIN    compositing: alpha clamp, and the smallest alpha that contributes
    T_STOP                   a pixel stops once its transmittance would fall below this
    CHANNELS, RGB/DEPTH/FLOW rendered feature channels [r, g, b, depth, flow_x, flow_y]
    CAM_SIZE                 floats in the camera buffer (CAM_* in cl/project4d_common.h)
"""
from __future__ import annotations

from typing import Tuple

TILE = 16                 # pixels per tile side (TILE in cl/common.h)

ALPHA_MAX = 0.99          # alpha clamp (3DGS): keeps 1 - alpha >= 0.01 so T can be divided back
ALPHA_MIN = 1.0 / 255.0   # contributions below one 8-bit level are skipped
T_STOP = 1e-4             # a pixel stops once its transmittance would fall below this

CHANNELS = 6              # r, g, b, depth, flow_x, flow_y
RGB, DEPTH, FLOW = slice(0, 3), 3, slice(4, 6)

CAM_SIZE = 20             # rotation (9), translation (3), fx, fy, cx, cy, near, campos (3)


def tile_grid(width: int, height: int, tile: int = TILE) -> Tuple[int, int]:
    """(tiles_x, tiles_y) covering a width x height image."""
    return (int(width) + tile - 1) // tile, (int(height) + tile - 1) // tile
