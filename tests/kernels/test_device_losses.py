"""The device image losses (cl/image_loss.cl) against the torch reference image_losses_ref (reference/losses.py)."""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pytest
import torch

from conftest import small
from endowave_cl.train.config import TrainConfig
from endowave_cl.train.device_losses import image_losses_and_grad, prepare_targets
from endowave_cl.reference.losses import image_losses_ref
from endowave_cl.wavelet.loss import WaveletConfig, wavelet_loss_and_grad

CHANNELS = {"depth": 3, "flow": 4}


def frame(seed, H, W, mask=True, depth=True, flow=True, flow_valid=True):
    rng = np.random.default_rng(seed)
    f = dict(image=rng.uniform(0, 1, (H, W, 3)).astype(np.float32))
    f["mask"] = (rng.uniform(size=(H, W)) > 0.3).astype(np.float32) if mask else None
    f["depth"] = np.where(rng.uniform(size=(H, W)) > 0.2, rng.uniform(1, 5, (H, W)), 0).astype(np.float32) \
        if depth else None
    f["flow"] = rng.normal(0, 2, (H, W, 2)).astype(np.float32) if flow else None
    f["flow_valid"] = (rng.uniform(size=(H, W)) > 0.25).astype(np.float32) if flow and flow_valid else None
    feats = np.concatenate([np.clip(f["image"] + rng.normal(0, 0.2, (H, W, 3)), 0, 1),
                            rng.uniform(1, 5, (H, W, 1)), rng.normal(0, 2, (H, W, 2))], -1).astype(np.float32)
    # a few exact matches: the L1 gradient there is 0, as torch's
    feats[0, 0, :3] = f["image"][0, 0]
    return f, feats


def reference(f, feats, cfg):
    x = torch.from_numpy(feats.copy()).requires_grad_(True)
    pred = {"image": x[..., :3], "depth": x[..., 3], "flow": x[..., 4:6]}
    tgt = {k: (None if v is None else torch.from_numpy(v)) for k, v in f.items()}
    total, parts = image_losses_ref(pred, tgt, cfg)
    total.backward()
    return float(total.detach()), parts, x.grad.numpy()


CASES = [dict(), dict(mask=False), dict(depth=False), dict(flow=False), dict(flow_valid=False),
         dict(mask=False, depth=False, flow=False)]
# the frames' flow errors are ~3 px: delta 2 puts many pixels on the Huber (linear) side, 1e9 none
DELTAS = [2.0, 1e9]


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("size", [(23, 31), (64, 48)])
@pytest.mark.parametrize("delta", DELTAS)
def test_device_losses_match_torch(rt, case, size, delta):
    H, W = size
    f, feats = frame(H + 100 * CASES.index(case), H, W, **case)
    cfg = TrainConfig(use_wavelet=False, lambda_flow=0.05, flow_huber_delta=delta)
    ref_total, ref_parts, ref_grad = reference(f, feats, cfg)
    tgt = prepare_targets(rt, f["image"], f["mask"], f["depth"], f["flow"], f["flow_valid"])
    total, parts, v = image_losses_and_grad(rt, cla.to_device(rt.queue, feats), tgt, cfg, CHANNELS)
    assert total == pytest.approx(ref_total, rel=1e-5, abs=1e-6)
    for k, val in ref_parts.items():
        assert parts[k] == pytest.approx(val, rel=1e-5, abs=1e-6), k
    assert set(ref_parts) <= set(parts)
    got = v.get()
    scale = np.abs(ref_grad).max()
    np.testing.assert_allclose(got, ref_grad, rtol=1e-4, atol=1e-5 * scale)
    if f["mask"] is not None:   # no gradient on tool pixels, in any channel
        assert not got[f["mask"] == 0].any()


@pytest.mark.parametrize("mask", [True, False])
def test_device_losses_add_the_wavelet_term(rt, mask):
    # the wavelet term's difference and masked gradient are fused into the image-loss kernels
    # (rgb_masked_diff, ssim_grad_combine): the same as the standalone wavelet loss, with and without a mask
    f, feats = frame(7, 33, 40, mask=mask)
    cfg = TrainConfig()
    wcfg = WaveletConfig()
    tgt = prepare_targets(rt, f["image"], f["mask"], f["depth"], f["flow"], f["flow_valid"])
    dev = cla.to_device(rt.queue, feats)
    t0, p0, v0 = image_losses_and_grad(rt, dev, tgt, TrainConfig(use_wavelet=False), CHANNELS)
    t1, p1, v1 = image_losses_and_grad(rt, dev, tgt, cfg, CHANNELS, wavelet_config=wcfg)
    wl, v_rgb = wavelet_loss_and_grad(rt, cla.to_device(rt.queue, np.ascontiguousarray(feats[..., :3])),
                                      tgt.image, tgt.mask if mask else None, wcfg)
    assert p1["wavelet"] == pytest.approx(wl, rel=1e-6)
    assert t1 == pytest.approx(t0 + cfg.lambda_wavelet * wl, rel=1e-6)
    want = v0.get()
    want[..., :3] += cfg.lambda_wavelet * v_rgb.get()
    np.testing.assert_allclose(v1.get(), want, rtol=1e-5, atol=1e-7)


def test_device_losses_psnr_and_perfect_prediction(rt):
    f, feats = frame(3, 20, 24, depth=False, flow=False)
    feats[..., :3] = f["image"]
    tgt = prepare_targets(rt, f["image"], f["mask"])
    total, parts, v = image_losses_and_grad(rt, cla.to_device(rt.queue, feats), tgt,
                                            TrainConfig(use_wavelet=False), CHANNELS)
    assert parts["l1"] == 0 and parts["ssim"] == pytest.approx(1.0, abs=1e-5) and parts["psnr"] == 120.0
    assert total == pytest.approx(0.0, abs=1e-5)
    np.testing.assert_allclose(v.get(), 0.0, atol=1e-6)


def test_device_losses_reject_mismatched_inputs(rt):
    f, feats = frame(9, 10, 12)
    tgt = prepare_targets(rt, f["image"], f["mask"])
    cfg = TrainConfig(use_wavelet=False)
    with pytest.raises(ValueError, match="does not match"):
        image_losses_and_grad(rt, cla.to_device(rt.queue, feats[:9]), tgt, cfg, CHANNELS)
    with pytest.raises(ValueError, match="do not fit"):
        image_losses_and_grad(rt, cla.to_device(rt.queue, np.ascontiguousarray(feats[..., :5])), tgt, cfg, CHANNELS)


@pytest.mark.oclgrind
def test_device_losses_tiny_oclgrind(rt):
    H, W = small(13, 9), small(17, 11)
    f, feats = frame(5, H, W)
    cfg = TrainConfig(lambda_flow=0.05)
    ref_total, _, ref_grad = reference(f, feats, TrainConfig(use_wavelet=False, lambda_flow=0.05))
    tgt = prepare_targets(rt, f["image"], f["mask"], f["depth"], f["flow"], f["flow_valid"])
    total, parts, v = image_losses_and_grad(rt, cla.to_device(rt.queue, feats), tgt, cfg, CHANNELS,
                                            wavelet_config=WaveletConfig())
    assert total == pytest.approx(ref_total + parts["wavelet"], rel=1e-5)
    assert np.isfinite(v.get()).all()


def _both_counts(rt, image, mask, cfg, feats, wcfg=None):
    """image_losses_and_grad of device_targets with the supervised count given as an int and left on
    the device: (total, parts, v_features) of each."""
    from endowave_cl.train.device_losses import device_targets
    count = int(mask.sum())
    img, m = cla.to_device(rt.queue, image), cla.to_device(rt.queue, mask)
    dev = cla.to_device(rt.queue, feats)
    out = []
    for supervised in (count, cla.to_device(rt.queue, np.array([count], np.int32))):
        tgt = device_targets(rt, img, m, supervised)
        assert (tgt.n_rgb is None) == (not isinstance(supervised, int))
        total, parts, v = image_losses_and_grad(rt, dev, tgt, cfg, CHANNELS, wavelet_config=wcfg)
        out.append((total, parts, v.get()))
    return out


@pytest.mark.parametrize("share", [0.0, 0.001, 0.4, 1.0])
@pytest.mark.parametrize("dssim", [0.2, 0.35])
def test_device_count_gives_the_same_bits(rt, share, dssim):
    """A target whose supervised pixel count stays on the device (an in-between target made there):
    the colour weights from the table rgb_weight_table keeps there, the count read back with the
    sums: the same loss values and the same gradient bits as with the count given by the host."""
    f, feats = frame(11, 29, 37, depth=False, flow=False)
    mask = (np.random.default_rng(3).uniform(size=(29, 37)) < share).astype(np.float32)
    cfg = TrainConfig(lambda_dssim=dssim, lambda_rgb=0.7)
    (t0, p0, v0), (t1, p1, v1) = _both_counts(rt, f["image"], mask, cfg, feats, WaveletConfig())
    assert t0 == t1 and p0 == p1
    assert np.array_equal(v0, v1)


def test_rgb_weight_table_rounds_as_the_arguments(rt):
    from endowave_cl.train.device_losses import rgb_denominator, rgb_weight_table, rgb_weights
    cfg = TrainConfig(lambda_rgb=0.9, lambda_dssim=0.3)
    table = rgb_weight_table(rt, cfg, 1000).get()
    assert table.shape == (1001, 2) and table.dtype == np.float32
    for c in (0, 1, 2, 3, 7, 333, 999, 1000):
        assert tuple(table[c]) == rgb_weights(cfg, rgb_denominator(c)), c


@pytest.mark.oclgrind
def test_device_count_tiny_oclgrind(rt):
    H, W = small(13, 9), small(17, 11)
    f, feats = frame(6, H, W, depth=False, flow=False)
    mask = (np.random.default_rng(4).uniform(size=(H, W)) < 0.5).astype(np.float32)
    (t0, _, v0), (t1, _, v1) = _both_counts(rt, f["image"], mask, TrainConfig(use_wavelet=False), feats)
    assert t0 == t1 and np.array_equal(v0, v1)
