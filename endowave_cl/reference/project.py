"""Torch reference of the project4d stage (docs/ARCHITECTURE.md "project4d").

Differentiable with torch autograd for every float output (radius / rect / tiles_touched are
integers); works in float32 (compared with the kernel) and float64 (finite differences).

Conventions fixed here and mirrored by cl/project4d_common.h:
- 4D rotation R = M_left(q_l) M_right(q_r): M_left(q) is the matrix of v -> q * v and
  M_right(q) of v -> v * q (Hamilton products), where the 4D vector (x, y, z, t) is read as
  the quaternion with components (w, x, y, z) = (x, y, z, t).  Both factors are orthogonal with
  determinant 1 for unit quaternions, so R is a rotation of R^4 (Yang et al., 4DGS).
- A Gaussian is culled (radius 0, empty rect, every float output 0 and no gradient) when:
  Sigma_tt is not > SIGMA_TT_MIN, the marginal m < MARGINAL_CULL (or not finite), the camera-space
  z of the conditional mean is < near, cov2d is non-finite or not positive definite, or the tile
  rectangle is empty.
- Tile rect: the tiles that the box means2d -+ 3 sqrt(lambda_max) reaches, narrowed to the box
  where opac G can reach ALPHA_MIN (``tight_extent``: the rasterizers skip every pixel outside it).
  A Gaussian whose opacity is below ALPHA_MIN keeps its radius but touches no tile.
- Flow channel: projection of mu_x|t_flow minus projection of mu_x|t; it is 0 (no gradient) when
  t_flow is None, when mu_x|t_flow is behind the near plane (its projection is undefined), or when
  the flow exceeds the image size (TILE * tiles per side) in x or y (a runaway velocity).
- SH view direction d = normalize(mu_x|t - campos), detached (no gradient through it).
"""
from __future__ import annotations

import math
from typing import Dict, Optional

import torch

from ..gaussians import LOWPASS, MARGINAL_CULL, TEASH_PERIOD, sh_basis_terms
from ..layout import ALPHA_MIN, TILE, tile_grid

SIGMA_TT_MIN = 1e-12   # temporal variance below this (std 1e-6 of the sequence) is degenerate: culled
RADIUS_MAX = 1 << 30   # the stored int radius saturates here (the rect uses the float radius)
# margins of the tight rect (cl/project4d_common.h p4_tight_rect): upper bound of ln, padding of q,
# relative and absolute (pixel) widening of the box, slack on the opacity test
LOG2_TANGENT_OFFSET = 0.913929
TIGHT_Q_PAD = 0.01
TIGHT_SLACK = 1.01
TIGHT_PAD = 0.5
TIGHT_OPAC_SLACK = 0.999


def quat_left_matrix(q: torch.Tensor) -> torch.Tensor:
    """[N, 4] quaternions (w, x, y, z) -> [N, 4, 4] matrices of v -> q * v."""
    a, b, c, d = q.unbind(-1)
    return torch.stack([
        torch.stack([a, -b, -c, -d], -1),
        torch.stack([b, a, -d, c], -1),
        torch.stack([c, d, a, -b], -1),
        torch.stack([d, -c, b, a], -1)], -2)


def quat_right_matrix(q: torch.Tensor) -> torch.Tensor:
    """[N, 4] quaternions (w, x, y, z) -> [N, 4, 4] matrices of v -> v * q."""
    p, q1, r, s = q.unbind(-1)
    return torch.stack([
        torch.stack([p, -q1, -r, -s], -1),
        torch.stack([q1, p, s, -r], -1),
        torch.stack([r, -s, p, q1], -1),
        torch.stack([s, r, -q1, p], -1)], -2)


def normalize_quat(q: torch.Tensor) -> torch.Tensor:
    """[N, 4] -> [N, 4] unit quaternions (norm clamped at 1e-12 so that 0 does not give NaN)."""
    return q / torch.sqrt(torch.clamp((q * q).sum(-1, keepdim=True), min=1e-24))


def rotation4d(quat_l: torch.Tensor, quat_r: torch.Tensor) -> torch.Tensor:
    """[N, 4], [N, 4] unnormalised -> [N, 4, 4] rotation M_left(q_l) M_right(q_r)."""
    return quat_left_matrix(normalize_quat(quat_l)) @ quat_right_matrix(normalize_quat(quat_r))


def covariance4d(scales: torch.Tensor, quat_l: torch.Tensor, quat_r: torch.Tensor) -> torch.Tensor:
    """log scales [N, 4] and quaternions -> Sigma = R S S^T R^T [N, 4, 4]."""
    M = rotation4d(quat_l, quat_r) * torch.exp(scales)[:, None, :]  # R diag(S), [N, 4, 4]
    return M @ M.transpose(-1, -2)


def condition_at(means: torch.Tensor, sigma: torch.Tensor, t: float):
    """Conditional of the 4D Gaussian at time t.

    means [N, 4], sigma [N, 4, 4] -> mu_x|t [N, 3], Sigma_x|t [N, 3, 3], marginal m [N].
    """
    sxx = sigma[:, :3, :3]   # [N, 3, 3]
    sxt = sigma[:, :3, 3]    # [N, 3]
    stt = sigma[:, 3, 3]     # [N]
    dt = t - means[:, 3]     # [N]
    mu = means[:, :3] + sxt * (dt / stt)[:, None]
    cov = sxx - sxt[:, :, None] * sxt[:, None, :] / stt[:, None, None]
    m = torch.exp(-0.5 * dt * dt / stt)
    return mu, cov, m


def conditional_mean(means: torch.Tensor, sigma: torch.Tensor, t: float) -> torch.Tensor:
    """mu_x|t [N, 3] alone (used for the flow time)."""
    return means[:, :3] + sigma[:, :3, 3] * ((t - means[:, 3]) / sigma[:, 3, 3])[:, None]


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Unit directions [N, 3] -> real SH basis values [N, (degree+1)^2] (3DGS order and signs)."""
    return torch.stack(sh_basis_terms(*dirs.unbind(-1), degree), -1)


def teash_cosines(phase: torch.Tensor, t: float) -> torch.Tensor:
    """phase [N, NT+1] -> cos(omega_n t + phi_n) [N, NT+1], with the n = 0 term fixed to 1."""
    nt1 = phase.shape[1]
    omega = 2.0 * math.pi * torch.arange(nt1, dtype=phase.dtype) / TEASH_PERIOD  # [NT+1]
    cosn = torch.cos(omega[None, :] * t + phase)
    return torch.cat([torch.ones_like(cosn[:, :1]), cosn[:, 1:]], 1)


def teash_colour(sh: torch.Tensor, phase: torch.Tensor, dirs: torch.Tensor, t: float) -> torch.Tensor:
    """sh [N, NT+1, K, 3], phase [N, NT+1], unit dirs [N, 3] -> colour [N, 3], clamped at 0."""
    K = sh.shape[2]
    Y = sh_basis(dirs, int(round(math.sqrt(K))) - 1)          # [N, K]
    cosn = teash_cosines(phase, t)                             # [N, NT+1]
    raw = 0.5 + torch.einsum("nikc,nk,ni->nc", sh, Y, cosn)    # [N, 3]
    return torch.clamp(raw, min=0.0)


def _camera_tensors(camera, dtype):
    V = torch.as_tensor(camera.viewmat, dtype=torch.float32).to(dtype)
    campos = torch.as_tensor(camera.campos, dtype=torch.float32).to(dtype)
    return V[:3, :3], V[:3, 3], campos


def _project_all(params, camera, t, t_flow, channels):
    """Every output for every Gaussian given, with no culling masks applied (may hold inf/NaN)."""
    dt = params["means"].dtype
    Rv, tv, campos = _camera_tensors(camera, dt)
    fx, fy, cx, cy = (float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy))
    sigma = covariance4d(params["scales"], params["quat_l"], params["quat_r"])
    mu, cov, m = condition_at(params["means"], sigma, t)
    p = mu @ Rv.T + tv                                   # [N, 3] camera space
    x, y, z = p.unbind(-1)
    zero = torch.zeros_like(z)
    # EWA Jacobian of (fx x/z + cx, fy y/z + cy), no clamping of x/z, y/z
    J = torch.stack([torch.stack([fx / z, zero, -fx * x / (z * z)], -1),
                     torch.stack([zero, fy / z, -fy * y / (z * z)], -1)], -2)  # [N, 2, 3]
    T = J @ Rv                                           # [N, 2, 3]
    cov2d = T @ cov @ T.transpose(-1, -2)                # [N, 2, 2]
    a = cov2d[:, 0, 0] + LOWPASS
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + LOWPASS
    det = a * c - b * b
    conic = torch.stack([c / det, -b / det, a / det], -1)
    mid = 0.5 * (a + c)
    lmax = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.0))
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], -1)
    opac = torch.sigmoid(params["opacity"]) * m
    dirs = (mu - campos).detach()
    dirs = dirs / torch.linalg.norm(dirs, dim=-1, keepdim=True)
    colour = teash_colour(params["sh"], params["phase"], dirs, t)
    feats = [colour, z[:, None]]
    if t_flow is not None:
        p2 = conditional_mean(params["means"], sigma, t_flow) @ Rv.T + tv
        ok2 = p2[:, 2] >= camera.near
        z2 = torch.where(ok2, p2[:, 2], torch.ones_like(p2[:, 2]))  # safe z: no NaN gradient
        proj2 = torch.stack([fx * p2[:, 0] / z2 + cx, fy * p2[:, 1] / z2 + cy], -1)
        flow = proj2 - means2d
        # a runaway flow (beyond the image size, in tiles) counts as undefined too
        flow_max = TILE * max(tile_grid(camera.width, camera.height))
        ok2 = ok2 & (flow.abs() <= flow_max).all(-1)
        flow = torch.where(ok2[:, None], flow, torch.zeros_like(means2d))
    else:
        flow = torch.zeros_like(means2d)
    feats.append(flow)
    features = torch.cat(feats, -1)                      # [N, 6]
    if channels <= 6:
        features = features[:, :channels]
    else:
        features = torch.cat([features, features.new_zeros(len(z), channels - 6)], -1)
    return dict(means2d=means2d, conic=conic, depth=z, opac=opac, features=features,
                lmax=lmax, det=det, m=m, stt=sigma[:, 3, 3], cov_a=a, cov_c=c)


def log_upper(x: torch.Tensor) -> torch.Tensor:
    """The kernel's upper bound of ln(x) for finite x > 0 (float32): x = 2^e m, m in [1, 2), and
    log2(m) <= m - LOG2_TANGENT_OFFSET (the tangent of the concave log2 at m = 1 / ln 2)."""
    bits = x.to(torch.float32).view(torch.int32)
    e = (bits >> 23).to(torch.float32) - 127.0
    m = ((bits & 0x007FFFFF) | 0x3F800000).view(torch.float32)
    return math.log(2.0) * (e + m - LOG2_TANGENT_OFFSET) + 1e-3


def tight_extent(opac, cov_a, cov_c, radius):
    """Half-widths (ex, ey) [N] in pixels of the box where opac exp(-d^T cov2d^-1 d / 2) can reach
    ALPHA_MIN, padded (TIGHT_*) and capped at the 3-sigma radius, and the mask of Gaussians whose
    opacity can reach ALPHA_MIN at all (float32, as the kernel)."""
    ratio = opac.to(torch.float32) * (1.0 / torch.tensor(ALPHA_MIN, dtype=torch.float32))   # as 1.0f / ALPHA_MIN
    reach = ratio >= TIGHT_OPAC_SLACK
    q = 2.0 * torch.clamp(log_upper(torch.clamp(ratio, min=1.0)), min=0.0) + TIGHT_Q_PAD
    ex = torch.minimum(torch.sqrt(q * torch.clamp(cov_a.to(torch.float32), min=0.0)) * TIGHT_SLACK + TIGHT_PAD, radius)
    ey = torch.minimum(torch.sqrt(q * torch.clamp(cov_c.to(torch.float32), min=0.0)) * TIGHT_SLACK + TIGHT_PAD, radius)
    return ex, ey, reach


def _tile_rect(m2, ex, ey, tiles_x, tiles_y):
    x0 = torch.clamp(torch.floor((m2[:, 0] - ex) / TILE), 0, tiles_x)
    x1 = torch.clamp(torch.ceil((m2[:, 0] + ex) / TILE), 0, tiles_x)
    y0 = torch.clamp(torch.floor((m2[:, 1] - ey) / TILE), 0, tiles_y)
    y1 = torch.clamp(torch.ceil((m2[:, 1] + ey) / TILE), 0, tiles_y)
    return torch.stack([x0, y0, x1, y1], -1).to(torch.int32)


def _radius_rect(means2d, lmax, width, height):
    """Integer radius [N], the float radius [N] and the 3-sigma tile rect [N, 4] from
    float32-rounded values (as the kernel)."""
    tiles_x, tiles_y = tile_grid(width, height)
    m2 = means2d.detach().to(torch.float32)
    r = torch.ceil(3.0 * torch.sqrt(lmax.detach().to(torch.float32)))
    rect = _tile_rect(m2, r, r, tiles_x, tiles_y)
    radius = torch.clamp(r, max=RADIUS_MAX).to(torch.int32)
    return radius, r, rect


def tight_rect(means2d, opac, cov_a, cov_c, radius_f, width, height):
    """The tile rect [N, 4] narrowed to tight_extent (empty where the opacity cannot reach ALPHA_MIN)."""
    tiles_x, tiles_y = tile_grid(width, height)
    ex, ey, reach = tight_extent(opac.detach(), cov_a.detach(), cov_c.detach(), radius_f)
    rect = _tile_rect(means2d.detach().to(torch.float32), ex, ey, tiles_x, tiles_y)
    return torch.where(reach[:, None], rect, torch.zeros_like(rect))


def project4d_ref(params: Dict[str, torch.Tensor], camera, t: float, t_flow: Optional[float] = None,
                  channels: int = 6) -> Dict[str, torch.Tensor]:
    """Reference project4d; see the module docstring.  params: the gaussians.py layout as tensors.
    Differentiable in means2d, conic, opac, features (depth is the detached sort key).

    Returns means2d [N, 2], conic [N, 3], depth [N], radius [N] int32, opac [N],
    features [N, C] ([r, g, b, depth, flow_x, flow_y]), rect [N, 4] int32, tiles_touched [N] int32.
    """
    N = params["means"].shape[0]
    dtype = params["means"].dtype
    # 1) which Gaussians survive, computed without gradients on all of them
    with torch.no_grad():
        allp = _project_all(params, camera, t, t_flow, channels)
        finite = (torch.isfinite(allp["means2d"]).all(-1) & torch.isfinite(allp["conic"]).all(-1)
                  & torch.isfinite(allp["lmax"]) & torch.isfinite(allp["features"]).all(-1))
        valid = ((allp["stt"] > SIGMA_TT_MIN) & (allp["m"] >= MARGINAL_CULL)
                 & (allp["depth"] >= camera.near) & (allp["det"] > 0) & finite)
        m2 = torch.where(valid[:, None], allp["means2d"], 0.0)
        radius, radius_f, rect = _radius_rect(m2, torch.where(valid, allp["lmax"], 0.0),
                                              camera.width, camera.height)
        valid &= (rect[:, 2] > rect[:, 0]) & (rect[:, 3] > rect[:, 1])
        rect = tight_rect(m2, torch.where(valid, allp["opac"], 0.0), allp["cov_a"], allp["cov_c"], radius_f,
                          camera.width, camera.height)
        area = (rect[:, 2] - rect[:, 0]) * (rect[:, 3] - rect[:, 1])
    idx = torch.nonzero(valid).flatten()
    # 2) differentiable outputs on the survivors only, scattered into zeros: culled rows stay 0 and
    #    receive exactly zero gradient, and no NaN from a culled row can leak into a gradient.
    sub = {k: v[idx] for k, v in params.items()}
    sp = _project_all(sub, camera, t, t_flow, channels)

    def scatter(v, shape):
        out = torch.zeros(shape, dtype=dtype)
        return out.index_put((idx,), v) if len(idx) else out

    out = dict(
        means2d=scatter(sp["means2d"], (N, 2)),
        conic=scatter(sp["conic"], (N, 3)),
        # depth is the sort key only (the kernel adjoint takes no v_depth): detached; its gradient
        # path is the depth feature channel features[:, 3]
        depth=scatter(sp["depth"], (N,)).detach(),
        opac=scatter(sp["opac"], (N,)),
        features=scatter(sp["features"], (N, channels)),
    )
    zi = torch.zeros_like(radius)
    out["radius"] = torch.where(valid, radius, zi)
    out["rect"] = torch.where(valid[:, None], rect, torch.zeros_like(rect))
    out["tiles_touched"] = torch.where(valid, area, zi).to(torch.int32)
    return out
