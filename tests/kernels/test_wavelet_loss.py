"""The wavelet loss: device loss/gradient vs the pure-torch version (autograd) and the numpy
reference, the autograd Function and module, masks, and the tiny Oclgrind cases."""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pytest
import torch

from endowave_cl.wavelet import filters as F
from endowave_cl.wavelet import ops
from endowave_cl.reference.wavelet import decompose_ref, wavelet_loss_ref
from endowave_cl.wavelet.loss import RationalWaveletLoss, WaveletConfig, WaveletLossFunction, wavelet_loss_and_grad


def dev(rt, x):
    return cla.to_device(rt.queue, np.ascontiguousarray(x, dtype=np.float32))


def images(shape, seed):
    rng = np.random.default_rng(seed)
    r = rng.random(shape).astype(np.float32)
    t = rng.random(shape).astype(np.float32)
    m = (rng.random(shape[:2]) > 0.3).astype(np.float32)
    return r, t, m


def torch_loss_grad(r, t, m, cfg):
    rr = torch.tensor(r, dtype=torch.float64, requires_grad=True)
    mm = None if m is None else torch.tensor(m, dtype=torch.float64)
    L = wavelet_loss_ref(rr, torch.tensor(t, dtype=torch.float64), mm, cfg)
    L.backward()
    return L.item(), rr.grad.numpy()


def test_default_config():
    c = WaveletConfig()
    assert c.levels == 2 and c.border == "reflect" and len(c.weights) == 4
    assert c.a == (c.q + 1) / c.q
    with pytest.raises(ValueError):
        WaveletConfig(q=0)
    with pytest.raises(ValueError):
        WaveletConfig(border="periodic")
    with pytest.raises(ValueError):
        WaveletConfig(weights=(1, 2, 3))


def test_loss_is_zero_for_identical_images(rt):
    r, _, m = images((19, 23, 3), 0)
    for mask in (None, dev(rt, m)):
        loss, v = wavelet_loss_and_grad(rt, dev(rt, r), dev(rt, r), mask)
        assert loss == 0.0
        assert not np.any(v.get())


@pytest.mark.parametrize("shape", [(19, 23, 3), (8, 5, 1), (30, 17, 6), (2, 3, 2)])
@pytest.mark.parametrize("q", [1, 2, 3])
@pytest.mark.parametrize("use_mask", [False, True])
def test_loss_and_grad_match_torch_autograd(rt, shape, q, use_mask):
    r, t, m = images(shape, q + 7 * use_mask)
    m = m if use_mask else None
    cfg = WaveletConfig(q=q, weights=(0.5, 1.0, 2.0, 3.0))
    loss, v = wavelet_loss_and_grad(rt, dev(rt, r), dev(rt, t), None if m is None else dev(rt, m), cfg)
    ref_loss, ref_grad = torch_loss_grad(r, t, m, cfg)
    assert loss == pytest.approx(ref_loss, rel=1e-5)
    assert loss == pytest.approx(F.loss_reference(r, t, q, 2, cfg.weights, m), rel=1e-5)
    assert v.shape == r.shape
    np.testing.assert_allclose(v.get(), ref_grad, rtol=1e-4, atol=1e-6 * np.abs(ref_grad).max())


def test_levels_and_weights_change_the_loss(rt):
    r, t, _ = images((24, 20, 3), 3)
    vals = {}
    for levels in (1, 2, 3):
        for w in ((1, 0, 0, 0), (0, 0, 0, 1)):
            cfg = WaveletConfig(q=2, levels=levels, weights=w)
            vals[levels, w] = wavelet_loss_and_grad(rt, dev(rt, r), dev(rt, t), None, cfg)[0]
            assert vals[levels, w] == pytest.approx(torch_loss_grad(r, t, None, cfg)[0], rel=1e-5)
    assert vals[2, (1, 0, 0, 0)] > vals[1, (1, 0, 0, 0)] > 0  # LL of level 2 is added
    assert vals[1, (0, 0, 0, 1)] > 0


@pytest.mark.parametrize("weights", [(0.0, 0.0, 2.0, 0.0), (0.0, 32.0, 32.0, 32.0), (3.0, 0.0, 0.0, 0.0)])
def test_bands_without_weight_are_left_out_exactly(rt, weights):
    # only the bands with a weight (and LL feeding the next level) are computed: the loss and the
    # gradient still match the full transform's
    r, t, m = images((29, 37, 3), 11)
    cfg = WaveletConfig(q=2, levels=3, weights=weights)
    loss, v = wavelet_loss_and_grad(rt, dev(rt, r), dev(rt, t), dev(rt, m), cfg)
    ref_loss, ref_grad = torch_loss_grad(r, t, m, cfg)
    assert loss == pytest.approx(ref_loss, rel=1e-5)
    np.testing.assert_allclose(v.get(), ref_grad, rtol=1e-4, atol=1e-6 * np.abs(ref_grad).max())


def test_no_weight_no_loss(rt):
    r, t, m = images((9, 8, 3), 12)
    loss, v = wavelet_loss_and_grad(rt, dev(rt, r), dev(rt, t), dev(rt, m), WaveletConfig(weights=(0, 0, 0, 0)))
    assert loss == 0.0
    assert v.shape == r.shape and not np.any(v.get())


def test_masked_pixels_do_not_matter(rt):
    r, t, m = images((16, 14, 3), 5)
    r2 = r.copy()
    r2[m == 0] += 5.0
    a = wavelet_loss_and_grad(rt, dev(rt, r), dev(rt, t), dev(rt, m))
    b = wavelet_loss_and_grad(rt, dev(rt, r2), dev(rt, t), dev(rt, m))
    assert a[0] == pytest.approx(b[0], rel=1e-6)
    assert not np.any(b[1].get()[m == 0])


def test_torch_version_matches_numpy_reference_transform():
    x = np.random.default_rng(2).standard_normal((17, 12, 2))
    for q in (1, 2, 4):
        got = decompose_ref(torch.tensor(x), q, 2)
        ref = F.decompose(x, q, 2)
        for j in range(2):
            for band in F.BANDS:
                np.testing.assert_allclose(got[j][band].numpy(), ref[j][band], atol=1e-12)


def test_autograd_function_and_module(rt):
    r, t, m = images((21, 18, 3), 9)
    cfg = WaveletConfig(q=2, weights=(1.0, 2.0, 3.0, 4.0))
    rr = torch.tensor(r, requires_grad=True)
    tt = torch.tensor(t, requires_grad=True)
    L = WaveletLossFunction.apply(rr, tt, torch.tensor(m), cfg, rt)
    (3.0 * L).backward()
    ref_loss, ref_grad = torch_loss_grad(r, t, m, cfg)
    assert L.item() == pytest.approx(ref_loss, rel=1e-5)
    np.testing.assert_allclose(rr.grad.numpy(), 3.0 * ref_grad, rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(tt.grad.numpy(), -3.0 * ref_grad, rtol=1e-4, atol=1e-7)
    # default runtime and config
    assert WaveletLossFunction.apply(torch.tensor(r), torch.tensor(t), None, None, None).item() == \
        pytest.approx(torch_loss_grad(r, t, None, WaveletConfig())[0], rel=1e-5)
    # the module: both backends, channel-first batches
    chw_r = torch.tensor(np.stack([r.transpose(2, 0, 1)] * 2))
    chw_t = torch.tensor(np.stack([t.transpose(2, 0, 1)] * 2))
    for backend in ("opencl", "torch"):
        mod = RationalWaveletLoss(cfg, backend=backend, layout="chw", rt=rt)
        assert mod(chw_r, chw_t, torch.tensor(np.stack([m, m]))).item() == pytest.approx(ref_loss, rel=1e-5)
        assert RationalWaveletLoss(cfg, backend=backend, rt=rt)(
            torch.tensor(r), torch.tensor(t)).item() == pytest.approx(torch_loss_grad(r, t, None, cfg)[0], rel=1e-5)


def test_torch_loss_gradcheck():
    r, t, m = images((6, 5, 2), 4)
    cfg = WaveletConfig(q=2)
    rr = torch.tensor(r, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda x: wavelet_loss_ref(x, torch.tensor(t, dtype=torch.float64), torch.tensor(m, dtype=torch.float64), cfg),
        (rr,), fast_mode=True)


def test_real_frame_loss_matches_torch(rt, pulling_scene):
    import imageio.v3 as iio
    img = iio.imread(sorted((pulling_scene / "images").glob("*.png"))[0]).astype(np.float32)[..., :3] / 255.0
    img = img[:96, :128]  # a crop keeps the test fast
    noisy = np.clip(img + np.random.default_rng(0).normal(0, 0.05, img.shape), 0, 1).astype(np.float32)
    loss, v = wavelet_loss_and_grad(rt, dev(rt, noisy), dev(rt, img))
    ref_loss, ref_grad = torch_loss_grad(noisy, img, None, WaveletConfig())
    assert loss == pytest.approx(ref_loss, rel=1e-4)
    np.testing.assert_allclose(v.get(), ref_grad, rtol=1e-3, atol=1e-4 * np.abs(ref_grad).max())


# ------------------------------------------------------------------------------------------------
# tiny cases also run under Oclgrind (python -m pytest --oclgrind -m oclgrind)
# ------------------------------------------------------------------------------------------------

@pytest.mark.oclgrind
def test_oclgrind_transform_and_adjoint_13x11x3(rt):
    x = np.random.default_rng(0).standard_normal((13, 11, 3)).astype(np.float32)
    q = 2
    got = ops.decompose(rt, dev(rt, x), q, 2)
    ref = F.decompose(x, q, 2)
    y = [{b: np.random.default_rng(j * 4 + i).standard_normal(ref[j][b].shape).astype(np.float32)
          for i, b in enumerate(F.BANDS)} for j in range(2)]
    ATy = ops.decompose_bwd(rt, [{b: dev(rt, y[j][b]) for b in F.BANDS} for j in range(2)], x.shape, q).get()
    lhs = 0.0
    for j in range(2):
        for b in F.BANDS:
            np.testing.assert_allclose(got[j][b].get(), ref[j][b], rtol=1e-5, atol=2e-6)
            lhs += float(np.sum(ref[j][b] * y[j][b]))
    assert lhs == pytest.approx(float(np.sum(x.astype(np.float64) * ATy)), rel=1e-5, abs=1e-5)


@pytest.mark.oclgrind
@pytest.mark.parametrize("shape, q, weights", [
    ((13, 11, 3), 1, (1.0, 2.0, 3.0, 4.0)),
    # the default weights (no LL term): the last level computes three bands, sumsq_scale's chunks
    # end inside a band (sizes not multiples of RED_CHUNK or of 8)
    ((17, 23, 3), 2, (0.0, 32.0, 32.0, 32.0))])
def test_oclgrind_loss_and_grad_with_mask(rt, shape, q, weights):
    r, t, m = images(shape, 1)
    cfg = WaveletConfig(q=q, weights=weights)
    loss, v = wavelet_loss_and_grad(rt, dev(rt, r), dev(rt, t), dev(rt, m), cfg)
    ref_loss, ref_grad = torch_loss_grad(r, t, m, cfg)
    assert loss == pytest.approx(ref_loss, rel=1e-5)
    np.testing.assert_allclose(v.get(), ref_grad, rtol=1e-4, atol=1e-6 * np.abs(ref_grad).max())


@pytest.mark.oclgrind
def test_oclgrind_short_axes_reflect_repeatedly(rt):
    # n = 1, 2, 3 < R: every reflection branch of conv_axis / conv_axis_bwd, plus resampling
    # (3, 8, 2) and (1, 8, 2) along axis 0: 16 elements per position, the 8-wide border runs
    for shape, axis in (((3, 2, 2), 1), ((3, 2, 2), 0), ((1, 2, 1), 0), ((3, 8, 2), 0), ((1, 8, 2), 0)):
        x = np.random.default_rng(axis).standard_normal(shape).astype(np.float32)
        y = np.random.default_rng(axis + 5).standard_normal(shape).astype(np.float32)
        f = np.random.default_rng(7).standard_normal(13).astype(np.float32)
        Ax = ops.conv_axis(rt, dev(rt, x), f, axis).get()
        np.testing.assert_allclose(Ax, F.conv_axis(x, f, axis), rtol=1e-5, atol=1e-5)
        ATy = ops.conv_axis_bwd(rt, dev(rt, y), f, axis).get()
        assert float(np.sum(Ax * y)) == pytest.approx(float(np.sum(x * ATy)), rel=1e-4, abs=1e-5)
        rs = ops.resample_axis(rt, dev(rt, x), 2, axis).get()
        np.testing.assert_allclose(rs, F.resample_axis(x, 2, axis), atol=1e-6)


@pytest.mark.oclgrind
@pytest.mark.parametrize("run", [ops.CONV_RUN_GPU, ops.CONV_RUN_CPU])
def test_oclgrind_conv_interior_runs(rt, run, monkeypatch):
    # lines long enough for the 8- and 16-element interior runs of conv_axis / conv_axis_bwd
    # (CONV_RUN), with a line length that is not a multiple of 8 or 16, along both image axes,
    # accumulating
    monkeypatch.setattr(ops, "conv_run", lambda rt: run)
    f = np.random.default_rng(3).standard_normal(13).astype(np.float32)
    for shape, axis in (((3, 37, 3), 1), ((29, 5, 3), 0), ((2, 53, 1), 1)):
        x = np.random.default_rng(axis).standard_normal(shape).astype(np.float32)
        y = np.random.default_rng(axis + 5).standard_normal(shape).astype(np.float32)
        Ax = ops.conv_axis(rt, dev(rt, x), f, axis).get()
        np.testing.assert_allclose(Ax, F.conv_axis(x, f, axis), rtol=1e-5, atol=1e-5)
        out = dev(rt, x)
        ATy = ops.conv_axis_bwd(rt, dev(rt, y), f, axis, out=out, accumulate=True).get() - x
        assert float(np.sum(Ax * y)) == pytest.approx(float(np.sum(x * ATy)), rel=1e-4, abs=1e-4)


@pytest.mark.oclgrind
@pytest.mark.parametrize("run", [ops.CONV_RUN_GPU, ops.CONV_RUN_CPU])
def test_oclgrind_conv_stack_terms(rt, run, monkeypatch):
    # the stacked convolutions with one to three terms per output slot, interior runs and borders,
    # and the adjoint accumulating
    monkeypatch.setattr(ops, "conv_run", lambda rt: run)
    f = np.random.default_rng(4).standard_normal((3, 13)).astype(np.float32)
    terms = (((1, 2),), ((0, 0), (1, 1)), ((1, 0), (0, 2), (1, 1)))
    for shape, axis in (((2, 3, 37, 3), 2), ((2, 29, 5, 3), 1)):
        x = np.random.default_rng(axis).standard_normal(shape).astype(np.float32)
        Ax = ops.conv_axis_stack(rt, dev(rt, x), f, terms, axis).get()
        np.testing.assert_allclose(Ax, F.conv_axis_stack(x, f, terms, axis), rtol=1e-5, atol=1e-5)
        back = tuple(tuple((t, g) for t, tt in enumerate(terms) for s2, g in tt if s2 == s) for s in range(2))
        y = np.random.default_rng(axis + 5).standard_normal(Ax.shape).astype(np.float32)
        out = dev(rt, x)
        ATy = ops.conv_axis_stack_bwd(rt, dev(rt, y), f, back, axis, out=out, accumulate=True).get() - x
        assert float(np.sum(Ax * y)) == pytest.approx(float(np.sum(x * ATy)), rel=1e-4, abs=1e-4)


def _row_kernels_case(monkeypatch, group, seed):
    """The CPU build of the row kernels with `group` work-items per line: (filters [3, 13], two
    output slots of one and two terms, the terms read the other way for the adjoint)."""
    monkeypatch.setattr(ops, "conv_run", lambda rt: ops.CONV_RUN_CPU)
    monkeypatch.setattr(ops, "rows_group", lambda rt: group)
    f = np.random.default_rng(seed).standard_normal((3, 13)).astype(np.float32)
    terms = (((1, 2),), ((0, 0), (1, 1)))
    back = tuple(tuple((t, g) for t, tt in enumerate(terms) for s2, g in tt if s2 == s) for s in range(2))
    return f, terms, back


@pytest.mark.oclgrind
@pytest.mark.parametrize("group", [1, 4])
def test_oclgrind_staged_row_passes(rt, group, monkeypatch):
    # the row passes staged in local memory (conv_axis_rows / conv_axis_rows_bwd) with one and with
    # four work-items per line (the barrier after staging), both borders, two-term slots, a line
    # length that ends in a short run, the adjoint accumulating
    f, terms, back = _row_kernels_case(monkeypatch, group, 6)
    x = np.random.default_rng(7).standard_normal((2, 3, 19, 3)).astype(np.float32)
    for border in ("zero", "reflect"):   # Ax: the reflect border's, for the adjoint below
        Ax = ops.conv_axis_stack(rt, dev(rt, x), f, terms, 2, border=border).get()
    np.testing.assert_allclose(Ax, F.conv_axis_stack(x, f, terms, 2), rtol=1e-5, atol=1e-5)
    y = np.random.default_rng(8).standard_normal(Ax.shape).astype(np.float32)
    out = dev(rt, x)
    ATy = ops.conv_axis_stack_bwd(rt, dev(rt, y), f, back, 2, out=out, accumulate=True).get() - x
    assert float(np.sum(Ax * y)) == pytest.approx(float(np.sum(x * ATy)), rel=1e-4, abs=1e-4)


@pytest.mark.oclgrind
@pytest.mark.parametrize("group", [1, 4])
def test_oclgrind_row_pass_and_resampling_in_one_launch(rt, group, monkeypatch):
    # a row pass and its resampling in one launch (conv_resample_rows) and their adjoint
    # (resample_conv_rows_bwd), two-term slots, accumulating, against the two launches each
    f, terms, back = _row_kernels_case(monkeypatch, group, 9)
    x = np.random.default_rng(13).standard_normal((2, 2, 19, 3)).astype(np.float32)
    got = ops.conv_resample_stack(rt, dev(rt, x), f, terms, 2, 2).get()
    np.testing.assert_allclose(got, F.resample_axis(F.conv_axis_stack(x, f, terms, 2), 2, 2), rtol=1e-5, atol=1e-5)
    v = np.random.default_rng(10).standard_normal(got.shape).astype(np.float32)
    ATv = ops.resample_conv_stack_bwd(rt, dev(rt, v), 2, 19, f, back, 2, out=dev(rt, x), accumulate=True).get()
    w = ops.resample_axis_bwd(rt, dev(rt, v), 2, 2, 19)
    ref = ops.conv_axis_stack_bwd(rt, w, f, back, 2, out=dev(rt, x), accumulate=True).get()
    np.testing.assert_allclose(ATv, ref, rtol=1e-6, atol=1e-6)
    assert float(np.sum(got * v)) == pytest.approx(float(np.sum(x * (ATv - x))), rel=1e-4, abs=1e-4)


@pytest.mark.oclgrind
def test_oclgrind_resample_runs_and_rows(rt):
    # both resampling layouts (short inner axis: a work-item per position; long: 8-element runs,
    # 8-wide in one sample) and their adjoints, accumulating, with a length not a multiple of 8
    for shape, axis in (((3, 37, 3), 1), ((29, 5, 3), 0), ((7, 4, 13), 0)):
        x = np.random.default_rng(axis).standard_normal(shape).astype(np.float32)
        rs = ops.resample_axis(rt, dev(rt, x), 2, axis).get()
        np.testing.assert_allclose(rs, F.resample_axis(x, 2, axis), atol=1e-6)
        y = np.random.default_rng(axis + 5).standard_normal(rs.shape).astype(np.float32)
        out = dev(rt, x)
        ATy = ops.resample_axis_bwd(rt, dev(rt, y), 2, axis, shape[axis], out=out, accumulate=True).get() - x
        assert float(np.sum(rs * y)) == pytest.approx(float(np.sum(x * ATy)), rel=1e-4, abs=1e-4)
