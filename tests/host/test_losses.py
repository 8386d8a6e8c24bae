"""Training losses (reference/losses.py): hand-computed values, an independent SSIM, gradcheck."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from endowave_cl.train.config import TrainConfig
from endowave_cl.reference.losses import (SSIM_C1, depth_loss, flow_loss, image_losses_ref, rgb_loss,
                                          rgb_terms, ssim_map)


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Tiny tensors: torch's thread pool costs more than it gives on a shared 2-core machine."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _rand(shape, seed, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(shape, generator=g, dtype=dtype)


def test_masked_l1_hand_value_ignores_tool_pixels():
    gt = _rand((16, 20, 3), 0)
    mask = torch.zeros(16, 20)
    mask[:, :8] = 1
    pred = gt + 0.1
    pred[:, 8:] += 5.0  # large error on tool pixels: must not count
    l1, _ = rgb_terms(pred, gt, mask)
    assert abs(float(l1) - 0.1) < 1e-6
    l1_all, _ = rgb_terms(pred, gt, None)
    assert abs(float(l1_all) - (0.1 * 8 + 5.1 * 12) / 20) < 1e-5


def test_identical_images_give_zero_rgb_loss_and_constant_ssim_formula():
    gt = _rand((12, 12, 3), 1)
    assert float(rgb_loss(gt.clone(), gt, (_rand((12, 12), 2) > 0.5).float())) == pytest.approx(0.0, abs=1e-6)
    # constant images a, b: away from the zero-padded border sigma = 0, so
    # SSIM = (2ab + C1) / (a^2 + b^2 + C1)
    a, b = 0.3, 0.7
    s = ssim_map(torch.full((20, 20, 3), a, dtype=torch.float64), torch.full((20, 20, 3), b, dtype=torch.float64))
    want = (2 * a * b + SSIM_C1) / (a * a + b * b + SSIM_C1)
    assert float(s[10, 10, 1]) == pytest.approx(want, rel=1e-9)


def test_ssim_map_matches_skimage_in_the_interior():
    skm = pytest.importorskip("skimage.metrics")
    x = _rand((30, 32, 3), 3, torch.float64)
    y = (x + 0.1 * _rand((30, 32, 3), 4, torch.float64)).clamp(0, 1)
    _, full = skm.structural_similarity(x.numpy(), y.numpy(), data_range=1.0, channel_axis=-1, full=True,
                                        gaussian_weights=True, sigma=1.5, use_sample_covariance=False)
    ours = ssim_map(x, y).numpy()
    np.testing.assert_allclose(ours[5:-5, 5:-5], full[5:-5, 5:-5], rtol=1e-6, atol=1e-8)


def test_depth_loss_uses_valid_gt_and_mask_only():
    gt = torch.tensor([[1.0, 0.0], [2.0, 3.0]])
    pred = torch.tensor([[1.5, 9.0], [2.0, 9.0]])
    mask = torch.tensor([[1.0, 1.0], [1.0, 0.0]])
    # valid: (0,0) err 0.5, (1,0) err 0; (0,1) gt invalid, (1,1) masked
    assert float(depth_loss(pred, gt, mask)) == pytest.approx(0.25)
    assert float(depth_loss(pred, gt, None)) == pytest.approx((0.5 + 0 + 6) / 3)


def test_flow_loss_is_mean_squared_endpoint_error_over_valid():
    gt = torch.zeros(2, 2, 2)
    pred = torch.zeros(2, 2, 2)
    pred[0, 0] = torch.tensor([3.0, 4.0])  # |e|^2 = 25
    pred[1, 1] = torch.tensor([100.0, 0.0])
    valid = torch.tensor([[1.0, 1.0], [0.0, 0.0]])
    assert float(flow_loss(pred, gt, valid, delta=math.inf)) == pytest.approx(12.5)
    assert float(flow_loss(pred, gt, torch.zeros(2, 2))) == 0.0  # nothing valid: 0, no NaN
    # Huber beyond delta: |e| = 5 > 4 costs 2 * 4 * 5 - 16 = 24; |e| = 100 on a valid pixel: 784
    assert float(flow_loss(pred, gt, valid, delta=4.0)) == pytest.approx(24 / 2)
    assert float(flow_loss(pred, gt, None, delta=4.0)) == pytest.approx((24 + 784) / 4)
    assert float(flow_loss(pred, gt, None, delta=6.0)) == pytest.approx((25 + 2 * 6 * 100 - 36) / 4)


def test_flow_loss_gradient_is_bounded_by_delta():
    pred = torch.tensor([[[1e6, 0.0], [0.0, 0.0]]], requires_grad=True)   # [1, 2, 2]
    gt = torch.tensor([[[0.0, 0.0], [1.0, 1.0]]])
    flow_loss(pred, gt, None, delta=4.0).backward()
    g = pred.grad[0]
    assert g[0].norm() == pytest.approx(2 * 4.0 / 2)            # 2 delta / n_pixels
    assert torch.allclose(g[1], torch.tensor([-1.0, -1.0]))     # quadratic: 2 e / 2


def test_gradcheck_float64():
    H, W = 7, 9
    pred = _rand((H, W, 3), 5, torch.float64).requires_grad_()
    gt = _rand((H, W, 3), 6, torch.float64)
    mask = (_rand((H, W), 7) > 0.3).double()
    assert torch.autograd.gradcheck(lambda p: rgb_loss(p, gt, mask), (pred,), eps=1e-6, atol=1e-6)
    d = _rand((H, W), 8, torch.float64).requires_grad_()
    gd = _rand((H, W), 9, torch.float64)
    gd[0, :] = 0
    assert torch.autograd.gradcheck(lambda p: depth_loss(p, gd, mask), (d,), eps=1e-6, atol=1e-6)
    f = _rand((H, W, 2), 10, torch.float64).requires_grad_()
    gf = _rand((H, W, 2), 11, torch.float64)
    assert torch.autograd.gradcheck(lambda p: flow_loss(p, gf, mask), (f,), eps=1e-6, atol=1e-6)
    assert torch.autograd.gradcheck(lambda p: flow_loss(3 * p, gf, mask, delta=0.5), (f,), eps=1e-6, atol=1e-6)


def test_image_losses_total_and_switches():
    H, W = 10, 12
    gt = {"image": _rand((H, W, 3), 12), "depth": 1 + _rand((H, W), 13), "mask": torch.ones(H, W),
          "flow": _rand((H, W, 2), 14), "flow_valid": torch.ones(H, W)}
    pred = {"image": _rand((H, W, 3), 15).requires_grad_(), "depth": _rand((H, W), 16).requires_grad_(),
            "flow": _rand((H, W, 2), 17).requires_grad_()}
    wav = lambda p, g, m: ((p - g) ** 2).mean()
    cfg = TrainConfig(lambda_depth=0.5, lambda_flow=0.01, lambda_wavelet=2.0)
    total, parts = image_losses_ref(pred, gt, cfg, wavelet_loss=wav)
    want = parts["rgb"] + 0.5 * parts["depth"] + 0.01 * parts["flow"] + 2.0 * parts["wavelet"]
    assert parts["total"] == pytest.approx(want, rel=1e-6)
    d = cfg.lambda_dssim
    assert parts["rgb"] == pytest.approx((1 - d) * parts["l1"] + d * (1 - parts["ssim"]), rel=1e-6)
    total.backward()
    assert all(pred[k].grad is not None and pred[k].grad.abs().sum() > 0 for k in pred)
    # switches and missing inputs leave terms out
    cfg2 = TrainConfig(use_flow=False, use_wavelet=False)
    _, parts2 = image_losses_ref(pred, {**gt, "depth": None}, cfg2)
    assert set(parts2) == {"l1", "ssim", "rgb", "total"} and parts2["total"] == pytest.approx(parts2["rgb"])
    _, parts3 = image_losses_ref(pred, gt, TrainConfig())  # no wavelet function: the caller adds it
    assert "wavelet" not in parts3 and "flow" in parts3
