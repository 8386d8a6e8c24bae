"""project4d host op: 4D Gaussians -> 2D splats at time t, and its adjoint (docs/ARCHITECTURE.md).

Kernels: cl/project4d.cl (forward), cl/project4d_bwd.cl (adjoint), shared math in
cl/project4d_common.h, each built as one of two variants (``project_lanes``).  Reference:
endowave_cl/reference/project.py.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional

import numpy as np
import pyopencl.array as cla

from .. import env     # every ENDOWAVE_* variable is parsed there, with a named error
from ..gaussians import LOWPASS, MARGINAL_CULL, TEASH_PERIOD
from ..layout import ALPHA_MIN, CAM_SIZE, CHANNELS, tile_grid
from .rasterize import VEC_WIDTH, raster_choice, simt_device
from .util import f32_literal

WORK_GROUP = 64        # work-items per group (scalar variant); one work-item per Gaussian
VEC_WORK_GROUP = 8     # work-items per group of the vector variant (each takes its lanes' Gaussians)

# Kernel variants (cl/project4d_common.h).  "scalar": one Gaussian per work-item, the GPU path
# (devices that report a SIMT width, DeviceCaps).  "vector": W Gaussians per work-item in floatW
# lanes (-DP4_VW=W), for devices that report none: CPU drivers such as PoCL run work-items as loops
# and do not vectorise the scalar kernels across them.  W is the rasterizer's lane count
# (ops.rasterize.raster_choice: its probe has checked that the driver generates correct code at
# that width); a CPU device whose rasterizer falls back to scalar runs the scalar kernels here too.
ENV_VARIANT = "ENDOWAVE_PROJECT_VARIANT"   # scalar | vector: force a variant (tests, benchmarks)
ENV_VEC_WIDTH = "ENDOWAVE_PROJECT_VW"      # force the lanes of the vector variant: 2, 4, 8 or 16
VARIANTS = ("scalar", "vector")
VEC_WIDTHS = (2, 4, 8, 16)


def project_lanes(rt) -> int:
    """Lanes of the project4d variant that runs on rt: 0 for the scalar kernels, else W.

    $ENDOWAVE_PROJECT_VARIANT / $ENDOWAVE_PROJECT_VW force a variant / lane count; else devices
    that report a SIMT width run the scalar kernels and the others the vector ones at the
    rasterizer's lane count (scalar where the rasterizer runs scalar)."""
    v = env.get(ENV_VARIANT)
    w = env.get(ENV_VEC_WIDTH)
    if v == "scalar":
        return 0
    if w:
        return w
    if v != "vector" and simt_device(rt):
        return 0
    ch = raster_choice(rt)
    if ch.variant == "vector":
        return ch.vw
    return VEC_WIDTH if v == "vector" else 0


def launch_lanes(rt, file: str, name: str, opts, n: int, *args, vec_opts=lambda lanes: []):
    """Build (variant options added; vec_opts(lanes): more for the vector variant) and launch
    a kernel written on cl/project4d_common.h's lanes (project4d, project4d_bwd, select's
    live_flags) over n Gaussians.  The vector kernels need N >= lanes (every lane a
    Gaussian: the last work-item ends at N); smaller scenes run the scalar kernels."""
    lanes = project_lanes(rt)
    if lanes and n >= lanes:
        # Oclgrind cannot create the kernel when its callees are always_inline (project4d_common.h)
        extra = ["-DP4_NO_FORCE_INLINE"] if getattr(rt, "is_oclgrind", False) else []
        k = rt.kernel(file, name, list(opts) + [f"-DP4_VW={lanes}"] + extra + vec_opts(lanes))
        rt.launch_1d(k, -(-n // lanes), VEC_WORK_GROUP, *args)
    else:
        rt.launch_1d(rt.kernel(file, name, opts), n, WORK_GROUP, *args)


@dataclass
class Projected:
    means2d: cla.Array        # [N, 2] float32
    conic: cla.Array          # [N, 3] float32 (inv00, inv01, inv11)
    depth: cla.Array          # [N] float32, camera-space z
    radius: cla.Array         # [N] int32, 0 = culled
    opac: cla.Array           # [N] float32, sigmoid(opacity) * marginal
    features: cla.Array       # [N, C] float32 [r, g, b, depth, flow_x, flow_y]
    rect: cla.Array           # [N, 4] int32 (x0, y0, x1, y1) exclusive, in tiles
    tiles_touched: cla.Array  # [N] int32
    color_inner: cla.Array    # [N, NT+1, 3] float32 per-frequency SH sums of the colour (read by the adjoint)
    camera: object = None      # the camera projected with ...
    camera_buf: object = None  # ... and its device buffer: project4d_bwd reuses it for the same camera

    def __len__(self) -> int:
        return int(self.radius.shape[0])


@dataclass
class ShGradFactors:
    """The gradient of the SH coefficients, v_sh [N, NT+1, K, 3], as per-Gaussian factors
    (cl/sh_grad.h): v_sh[i, f, k, c] = (gcol[i, c] Y[i, k]) cos[i, f], zero rows for culled Gaussians.
    factors [N, NT + 4 + K] float32, each row cos_f (f = 0..NT), gcol_c (c = 0..2), Y_k (k = 0..K-1)
    (SHF_* in cl/sh_grad.h).  DeviceAdam forms the products in its kernel, and the NaN guard
    (ops.util.nonfinite_flag) checks the factors; ``get`` forms them on the host (the same float32
    products: the same bits as project4d_bwd's full v_sh)."""
    factors: cla.Array
    nt: int
    K: int

    @property
    def shape(self):
        return (int(self.factors.shape[0]), self.nt + 1, self.K, 3)

    @property
    def dtype(self):
        return self.factors.dtype

    def get(self) -> np.ndarray:
        f = self.factors.get()
        nt = self.nt
        cos, gcol, Y = f[:, :nt + 1], f[:, nt + 1:nt + 4], f[:, nt + 4:]
        gY = gcol[:, None, :] * Y[:, :, None]                 # [N, K, 3]
        return gY[:, None, :, :] * cos[:, :, None, None]    # [N, NT+1, K, 3]


def sh_factor_width(nt: int, K: int) -> int:
    """Factors per Gaussian of a ShGradFactors (SHF_SIZE in cl/sh_grad.h)."""
    return nt + 4 + K


def _dims(params):
    sh = params["sh"]
    n = int(params["means"].shape[0])
    nt = int(sh.shape[1]) - 1
    K = int(sh.shape[2])
    degree = int(round(np.sqrt(K))) - 1
    if (degree + 1) ** 2 != K or not 0 <= degree <= 3:
        raise ValueError(f"sh has {K} bases per frequency; expected (L+1)^2 with L in 0..3")
    return n, nt, K, degree


def _options(rt, degree: int, nt: int, channels: int):
    opts = [f"-DSH_DEGREE={degree}", f"-DNT={nt}", f"-DCHANNELS={channels}",
            f"-DTEASH_PERIOD={float(TEASH_PERIOD)!r}f", f"-DMARGINAL_CULL={float(MARGINAL_CULL)!r}f",
            f"-DLOWPASS={f32_literal(LOWPASS)}",
            f"-DALPHA_MIN={f32_literal(ALPHA_MIN)}"]   # the tight tile rect (project4d.cl)
    # correctly rounded / and sqrt (where the device offers them; OpenCL 1.2 allows the option only
    # then) bring the float radius / rect closer to the torch reference at ceil / floor boundaries
    fp = getattr(rt.device, "single_fp_config", 0)
    if fp & rt.cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT:
        opts.append("-cl-fp32-correctly-rounded-divide-sqrt")
    return opts


def camera_buffer(rt, camera) -> cla.Array:
    """The camera as the kernels read it: rotation (9), translation (3), fx, fy, cx, cy, near, campos (3)."""
    V = np.asarray(camera.viewmat, np.float32)
    buf = np.concatenate([V[:3, :3].reshape(-1), V[:3, 3],
                          np.array([camera.fx, camera.fy, camera.cx, camera.cy, camera.near], np.float32),
                          camera.campos.astype(np.float32)]).astype(np.float32)
    assert buf.size == CAM_SIZE
    return cla.to_device(rt.queue, buf)


def _tiles(camera):
    return tile_grid(camera.width, camera.height)


def _check_params(params, n):
    for name in ("means", "scales", "quat_l", "quat_r", "opacity", "sh", "phase"):
        a = params[name]
        if a.dtype != np.float32 or not a.flags.c_contiguous or int(a.shape[0]) != n:
            raise ValueError(f"params[{name!r}] must be C-contiguous float32 with {n} rows")


def project4d(rt, params: Dict[str, cla.Array], camera, t: float, t_flow: Optional[float] = None,
              channels: int = CHANNELS) -> Projected:
    """Project every Gaussian at time t (flow to t_flow when given); see docs/ARCHITECTURE.md."""
    n, nt, K, degree = _dims(params)
    f32, i32 = np.float32, np.int32
    out = Projected(
        means2d=rt.empty((n, 2), f32), conic=rt.empty((n, 3), f32),
        depth=rt.empty((n,), f32), radius=rt.empty((n,), i32),
        opac=rt.empty((n,), f32), features=rt.empty((n, channels), f32),
        rect=rt.empty((n, 4), i32), tiles_touched=rt.empty((n,), i32),
        color_inner=rt.empty((n, nt + 1, 3), f32))
    if n == 0:
        return out
    _check_params(params, n)
    tiles_x, tiles_y = _tiles(camera)
    cam = camera_buffer(rt, camera)
    out.camera, out.camera_buf = camera, cam
    launch_lanes(rt, "project4d.cl", "project4d", _options(rt, degree, nt, channels), n,
                 np.int32(n), params["means"].data, params["scales"].data, params["quat_l"].data,
                 params["quat_r"].data, params["opacity"].data, params["sh"].data, params["phase"].data,
                 cam.data, np.float32(t), np.float32(0.0 if t_flow is None else t_flow),
                 np.int32(t_flow is not None), np.int32(tiles_x), np.int32(tiles_y),
                 out.means2d.data, out.conic.data, out.depth.data, out.radius.data, out.opac.data,
                 out.features.data, out.rect.data, out.tiles_touched.data, out.color_inner.data)
    return out


def project4d_bwd(rt, params: Dict[str, cla.Array], camera, t: float, t_flow: Optional[float],
                  proj: Projected, v_means2d: cla.Array, v_conic: cla.Array, v_opac: cla.Array,
                  v_features: cla.Array, sh_factors: bool = False) -> Dict[str, cla.Array]:
    """Adjoint of project4d: gradients of every parameter (zero for culled Gaussians).

    v_means2d [N, 2], v_conic [N, 3], v_opac [N], v_features [N, C] ->
    v_means [N, 4], v_scales [N, 4], v_quat_l [N, 4], v_quat_r [N, 4], v_opacity [N],
    v_sh [N, NT+1, K, 3], v_phase [N, NT+1].  The SH view direction is not differentiated.
    sh_factors: v_sh comes as a ShGradFactors (NT + 4 + K floats per Gaussian instead of
    3 (NT + 1) K), for DeviceAdam, which forms the same values.
    """
    n, nt, K, degree = _dims(params)
    shapes = {"v_means": (n, 4), "v_scales": (n, 4), "v_quat_l": (n, 4), "v_quat_r": (n, 4),
              "v_opacity": (n,), "v_sh": (n, nt + 1, K, 3), "v_phase": (n, nt + 1)}
    if sh_factors:
        shapes["v_sh"] = (n, sh_factor_width(nt, K))
    grads = {k: rt.empty(s, np.float32) for k, s in shapes.items()}
    sh_buf = grads["v_sh"]
    if sh_factors:
        grads["v_sh"] = ShGradFactors(sh_buf, nt, K)
    if n == 0:
        return grads
    _check_params(params, n)
    channels = int(v_features.shape[1])
    tiles_x, tiles_y = _tiles(camera)
    cam = proj.camera_buf if proj.camera is camera and proj.camera_buf is not None else camera_buffer(rt, camera)

    def nt_store(lanes):
        # non-temporal whole-vector stores of v_sh rows (p4_st_rows): only where every row block
        # of lanes floats is aligned to its size (rows a multiple of lanes floats, buffer aligned)
        vbytes = 4 * lanes
        base_align = int(getattr(rt.device, "mem_base_addr_align", 0) or 0) // 8
        ok = ((nt + 1) * K * 3) % lanes == 0 and base_align % vbytes == 0 and sh_buf.offset % vbytes == 0
        return ["-DP4_NT_STORE=1"] if ok and not sh_factors else []
    opts = _options(rt, degree, nt, channels) + (["-DP4_SH_FACTORS"] if sh_factors else [])
    launch_lanes(rt, "project4d_bwd.cl", "project4d_bwd", opts, n,
                 np.int32(n), params["means"].data, params["scales"].data, params["quat_l"].data,
                 params["quat_r"].data, params["opacity"].data, proj.color_inner.data, params["phase"].data,
                 cam.data, np.float32(t), np.float32(0.0 if t_flow is None else t_flow),
                 np.int32(t_flow is not None), np.int32(tiles_x), np.int32(tiles_y),
                 proj.radius.data, v_means2d.data, v_conic.data, v_opac.data, v_features.data,
                 grads["v_means"].data, grads["v_scales"].data, grads["v_quat_l"].data, grads["v_quat_r"].data,
                 grads["v_opacity"].data, sh_buf.data, grads["v_phase"].data, vec_opts=nt_store)
    return grads
