"""The model layer (gaussians.py, checkpoint.py): numpy rotation and covariance equal the torch
reference's, and export, evaluation and the viewer import neither torch nor train/."""
from __future__ import annotations

import subprocess
import sys

import numpy as np

from endowave_cl.gaussians import Gaussians, covariance_4d, normalize_quat, rotation_4d


def test_rotation_and_covariance_equal_the_torch_reference():
    import torch
    from endowave_cl.reference.project import covariance4d, rotation4d
    g = Gaussians.random(200, seed=1)
    g.quat_l[0] = 0.0                       # a zero quaternion: 0 (clamped norm), not NaN, in both
    R_ref = rotation4d(torch.from_numpy(g.quat_l.astype(np.float64)),
                       torch.from_numpy(g.quat_r.astype(np.float64))).numpy()
    cov_ref = covariance4d(torch.from_numpy(g.scales.astype(np.float64)),
                           torch.from_numpy(g.quat_l.astype(np.float64)),
                           torch.from_numpy(g.quat_r.astype(np.float64))).numpy()
    R = rotation_4d(g)
    assert R.shape == (200, 4, 4) and R.dtype == np.float64
    np.testing.assert_allclose(R, R_ref, rtol=0, atol=1e-15)   # the same formulas; the last bit may differ
    np.testing.assert_allclose(covariance_4d(g), cov_ref, rtol=1e-12, atol=1e-16)
    np.testing.assert_array_equal(R[0], 0.0)
    np.testing.assert_allclose(R[1:] @ np.swapaxes(R[1:], -1, -2), np.broadcast_to(np.eye(4), (199, 4, 4)),
                               atol=1e-14)


def test_normalize_quat_unit_and_zero():
    q = normalize_quat(np.array([[0.0, 0.0, 0.0, 0.0], [0.0, 3.0, 0.0, 4.0]]))
    np.testing.assert_array_equal(q[0], 0.0)
    np.testing.assert_allclose(q[1], [0.0, 0.6, 0.0, 0.8])


def test_export_eval_viewer_import_neither_torch_nor_train():
    code = ("import sys\n"
            "import endowave_cl.export_ply, endowave_cl.evaluation, endowave_cl.viewer, endowave_cl.checkpoint\n"
            "import endowave_cl.commands.export, endowave_cl.commands.view\n"
            "from endowave_cl.gaussians import Gaussians, covariance_4d\n"
            "covariance_4d(Gaussians.random(3))\n"
            "bad = sorted(m for m in sys.modules if m == 'torch' or m.startswith('endowave_cl.train'))\n"
            "print(bad)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]", r.stdout
