"""3DGS PLY export at a time t (export_ply.py), parsed back by hand."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from endowave_cl.export_ply import export_ply, matrix_to_quaternion, ply_property_names
from endowave_cl.gaussians import Gaussians
from endowave_cl.reference.project import condition_at, covariance4d, teash_cosines


def read_ply(path):
    """Minimal binary little-endian PLY reader: (property names, data [N, P])."""
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    lines = raw[:end].decode("ascii").splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    n = int([ln for ln in lines if ln.startswith("element vertex")][0].split()[2])
    props = [ln.split()[2] for ln in lines if ln.startswith("property float")]
    assert len(raw) - end == n * len(props) * 4
    return props, np.frombuffer(raw[end:], "<f4").reshape(n, len(props))


def quat_to_matrix(q):
    """3DGS build_rotation: (w, x, y, z) -> R."""
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def test_export_centre_covariance_colour_and_culling(tmp_path):
    g = Gaussians.random(40, seed=3)
    g.means[:, 3] = np.linspace(0, 1, 40)
    g.scales[:, 3] = math.log(0.1)
    t = 0.45
    n = export_ply(tmp_path / "m.ply", g, t)
    props, data = read_ply(tmp_path / "m.ply")
    assert props == ply_property_names() and len(props) == 62

    # independent expectation from the renderer's torch reference
    tg = {k: torch.from_numpy(v.astype(np.float64)) for k, v in g.as_dict().items()}
    sigma = covariance4d(tg["scales"], tg["quat_l"], tg["quat_r"])
    mu, cov, m = condition_at(tg["means"], sigma, t)
    keep = (m >= 0.05).numpy()
    assert n == keep.sum() and 0 < n < 40 and len(data) == n
    mu, cov, m = mu.numpy()[keep], cov.numpy()[keep], m.numpy()[keep]
    cosn = teash_cosines(tg["phase"], t).numpy()[keep]
    sh_t = np.einsum("nikc,ni->nkc", g.sh[keep].astype(np.float64), cosn)   # [n, 16, 3]
    col = {p: i for i, p in enumerate(props)}
    for i in range(n):
        r = data[i]
        np.testing.assert_allclose(r[[col["x"], col["y"], col["z"]]], mu[i], rtol=1e-5, atol=1e-6)
        S = np.exp(r[[col["scale_0"], col["scale_1"], col["scale_2"]]].astype(np.float64))
        R = quat_to_matrix(r[[col["rot_0"], col["rot_1"], col["rot_2"], col["rot_3"]]].astype(np.float64))
        np.testing.assert_allclose(R @ np.diag(S * S) @ R.T, cov[i], rtol=1e-4, atol=1e-8)
        np.testing.assert_allclose(r[[col["f_dc_0"], col["f_dc_1"], col["f_dc_2"]]], sh_t[i, 0], rtol=1e-5, atol=1e-6)
        rest = r[[col[f"f_rest_{j}"] for j in range(45)]].reshape(3, 15)     # channel-major
        np.testing.assert_allclose(rest, sh_t[i, 1:].T, rtol=1e-5, atol=1e-6)
        o = 1 / (1 + math.exp(-float(g.opacity[keep][i]))) * m[i]
        assert 1 / (1 + math.exp(-float(r[col["opacity"]]))) == pytest.approx(o, rel=1e-4)
        assert np.all(r[[col["nx"], col["ny"], col["nz"]]] == 0)


def test_export_scale_multiplies_positions_and_sizes_only(tmp_path):
    g = Gaussians.random(30, seed=5)
    g.means[:, 3] = 0.5
    export_ply(tmp_path / "a.ply", g, 0.5)
    export_ply(tmp_path / "b.ply", g, 0.5, scale=2.5)
    props, a = read_ply(tmp_path / "a.ply")
    b = read_ply(tmp_path / "b.ply")[1]
    col = {p: i for i, p in enumerate(props)}
    xyz = [col["x"], col["y"], col["z"]]
    logs = [col["scale_0"], col["scale_1"], col["scale_2"]]
    np.testing.assert_allclose(b[:, xyz], 2.5 * a[:, xyz], rtol=1e-6)
    np.testing.assert_allclose(b[:, logs], a[:, logs] + math.log(2.5), rtol=1e-5, atol=1e-5)
    rest = [i for i in range(len(props)) if i not in xyz + logs]
    np.testing.assert_array_equal(b[:, rest], a[:, rest])


def test_low_degree_padding_empty_and_atomic(tmp_path):
    g = Gaussians.random(3, seed=1, degree=1, nt=1)
    g.means[:, 3] = 0.5
    export_ply(tmp_path / "a.ply", g, 0.5)
    props, data = read_ply(tmp_path / "a.ply")
    rest = data[:, 9:54].reshape(-1, 3, 15)
    assert np.all(rest[:, :, 3:] == 0) and np.any(rest[:, :, :3] != 0)
    assert export_ply(tmp_path / "e.ply", Gaussians.empty(), 0.0) == 0
    assert read_ply(tmp_path / "e.ply")[1].shape == (0, 62)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.ply", "e.ply"]  # no temporary files


def test_matrix_to_quaternion_round_trip():
    rng = np.random.default_rng(0)
    q = rng.standard_normal((50, 4))
    q[:5] = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0, 1e-9, 1, 0]]
    R = np.stack([quat_to_matrix(x) for x in q])
    back = np.stack([quat_to_matrix(x) for x in matrix_to_quaternion(R)])
    np.testing.assert_allclose(back, R, atol=1e-9)
