"""OpenCL rational-wavelet kernels against the numpy reference; dot-product adjoint tests."""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pytest

from conftest import small
from endowave_cl.wavelet import filters as F
from endowave_cl.wavelet import ops

BANDS = F.BANDS


def dev(rt, x):
    return cla.to_device(rt.queue, np.ascontiguousarray(x, dtype=np.float32))


def rand(shape, seed):
    return np.random.default_rng(seed).standard_normal(shape).astype(np.float32)


def dot(a, b):
    return float(np.sum(np.asarray(a, np.float64) * np.asarray(b, np.float64)))


# (shape, axis): short axes (n < R, n = 1, 2) exercise the repeated reflection; the longer ones
# the kernels' 8- and 16-element interior runs (CONV_RUN), with line lengths n * inner that are not
# multiples of 8 or 16 (runs that end early) and inner = 1 (a run spans 8 or 16 positions of the axis);
# inner >= 8 or 16 along axis 0 the 8-wide border runs within one position (n = 1 and 2 included),
# and inner = 37 runs that cross a position
CONV_CASES = [((5, 7, 3), 1), ((5, 7, 3), 0), ((1, 9, 2), 1), ((3, 2, 1), 1), ((2, 4, 3), 0),
              ((33, 21, 3), 1), ((33, 21, 3), 0), ((17,), 0), ((6, 5, 4, 2), 2),
              ((7, 41, 5), 1), ((45, 13, 3), 0), ((3, 61), 1), ((70,), 0),
              ((1, 40), 0), ((2, 16, 2), 0), ((19, 37, 1), 0)]


@pytest.fixture(params=[ops.CONV_RUN_GPU, ops.CONV_RUN_CPU], ids=lambda r: f"run{r}")
def conv_run(request, monkeypatch):
    """Both builds of the convolution kernels (CONV_RUN 8, the GPUs', and 16, the CPUs') on this device."""
    monkeypatch.setattr(ops, "conv_run", lambda rt: request.param)
    return request.param


@pytest.mark.parametrize("shape,axis", CONV_CASES)
@pytest.mark.parametrize("flen", [1, 3, 9, 13, 17])
def test_conv_axis_matches_reference(rt, conv_run, shape, axis, flen):
    x = rand(shape, flen)
    f = rand(flen, flen + 1)  # asymmetric: catches a flipped (correlation) kernel
    got = ops.conv_axis(rt, dev(rt, x), f, axis).get()
    np.testing.assert_allclose(got, F.conv_axis(x, f, axis), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("shape,axis", CONV_CASES)
@pytest.mark.parametrize("flen", [1, 11, 13])
def test_conv_axis_zero_border_and_its_adjoint(rt, conv_run, shape, axis, flen):
    """border="zero": numpy's 'same' convolution per line; adjoint = reversed filter, same border."""
    x, y, f = rand(shape, flen + 2), rand(shape, flen + 3), rand(flen, flen + 4)
    got = ops.conv_axis(rt, dev(rt, x), f, axis, border="zero").get()
    ref = np.apply_along_axis(lambda line: np.convolve(line.astype(np.float64), f, "full")[flen // 2:][:line.size],
                              axis, x)
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5)
    ATy = ops.conv_axis(rt, dev(rt, y), f[::-1].copy(), axis, border="zero").get()
    assert dot(got, y) == pytest.approx(dot(x, ATy), rel=1e-5, abs=1e-4)


@pytest.mark.parametrize("shape,axis", CONV_CASES)
@pytest.mark.parametrize("flen", [3, 13, 17])
def test_conv_axis_adjoint_dot_product(rt, conv_run, shape, axis, flen):
    x, y, f = rand(shape, 1), rand(shape, 2), rand(flen, 3)
    Ax = ops.conv_axis(rt, dev(rt, x), f, axis).get()
    ATy = ops.conv_axis_bwd(rt, dev(rt, y), f, axis).get()
    lhs, rhs = dot(Ax, y), dot(x, ATy)
    assert abs(lhs - rhs) <= 1e-5 * (1 + np.abs(Ax * y).sum())
    # and elementwise against the explicit transpose of the reference operator
    n = shape[axis]
    M = np.stack([F.conv_axis(np.eye(n)[i], f, 0) for i in range(n)], axis=1)  # [n_out, n_in]
    ref = np.moveaxis(np.tensordot(M.T, np.moveaxis(y.astype(np.float64), axis, 0), axes=(1, 0)), 0, axis)
    np.testing.assert_allclose(ATy, ref, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("axis", [0, 1])
def test_conv_adjoint_accumulates_over_interior_runs(rt, conv_run, axis):
    y, f, base = rand((37, 29, 3), 11), rand(13, 12), rand((37, 29, 3), 13)
    out = dev(rt, base)
    ops.conv_axis_bwd(rt, dev(rt, y), f, axis, out=out, accumulate=True)
    np.testing.assert_allclose(out.get(), base + ops.conv_axis_bwd(rt, dev(rt, y), f, axis).get(), atol=1e-5)


# stacks of 3 slots, output slots with 1 to 3 terms (a slot and a filter used twice, in any order)
STACK_TERMS = (((2, 1),), ((0, 0), (1, 2)), ((1, 1), (0, 1), (2, 0)), ((0, 2),))


@pytest.mark.parametrize("shape, axis", [((3, 5, 7, 3), 2), ((3, 33, 21, 3), 1), ((3, 33, 21, 3), 2),
                                         ((3, 45, 13, 3), 1), ((3, 2, 4, 1), 1), ((3, 70), 1)])
@pytest.mark.parametrize("border", ["reflect", "zero"])
def test_conv_axis_stack_matches_reference(rt, conv_run, shape, axis, border):
    x = rand(shape, 3)
    f = rand((3, 13), 4)
    got = ops.conv_axis_stack(rt, dev(rt, x), f, STACK_TERMS, axis, border=border).get()
    assert got.shape == (len(STACK_TERMS),) + shape[1:]
    if border == "reflect":
        np.testing.assert_allclose(got, F.conv_axis_stack(x, f, STACK_TERMS, axis), rtol=1e-5, atol=1e-5)
    # each output slot is, bit for bit, its terms' single convolutions added in order
    for t, terms in enumerate(STACK_TERMS):
        one = [ops.conv_axis(rt, dev(rt, x[s]), f[g], axis - 1, border=border).get() for s, g in terms]
        np.testing.assert_array_equal(got[t], sum(one[1:], one[0]))


# row passes (inner < CONV_RUN), which the staged kernels take: lines shorter than the filter (the
# forward reflects repeatedly, the adjoint keeps the unstaged kernel), lengths that end in a short
# run, inner 1 to 9
ROW_CASES = [((5, 7, 3), 1), ((33, 21, 3), 1), ((7, 41, 5), 1), ((3, 61), 1), ((1, 9, 2), 1), ((40, 37, 9), 1),
             ((6, 5, 4, 2), 2), ((12, 100, 1), 1), ((4, 15, 3), 1), ((2, 2, 3), 1)]


@pytest.mark.parametrize("shape,axis", ROW_CASES)
@pytest.mark.parametrize("flen", [3, 13, 17])
@pytest.mark.parametrize("group", [1, 5, 64])
def test_staged_row_passes_give_the_unstaged_bits(rt, conv_run, monkeypatch, shape, axis, flen, group):
    """conv_axis_rows / conv_axis_rows_bwd (a row pass's lines staged in local memory, one
    work-group of `group` work-items per line) give the unstaged kernels' bits: both borders, the
    adjoint alone and accumulating, and a stack whose output slots have one to three terms."""
    monkeypatch.setattr(ops, "rows_group", lambda rt: group)
    staged = []
    plain = ops._staged_rows_floats
    monkeypatch.setattr(ops, "_staged_rows_floats", lambda *a: staged.append(plain(*a)) or staged[-1])
    x, y, f = rand(shape, flen), rand(shape, flen + 1), rand(flen, flen + 2)
    xs, fs = rand((3,) + shape, flen + 3), rand((3, flen), flen + 4)
    back = tuple(tuple((t, g) for t, terms in enumerate(STACK_TERMS) for s2, g in terms if s2 == s) for s in range(3))
    ys = rand((len(STACK_TERMS),) + shape, flen + 5)

    def run_all():
        out = dev(rt, x)
        ops.conv_axis_bwd(rt, dev(rt, y), f, axis, out=out, accumulate=True)
        return [ops.conv_axis(rt, dev(rt, x), f, axis).get(),
                ops.conv_axis(rt, dev(rt, x), f, axis, border="zero").get(),
                ops.conv_axis_bwd(rt, dev(rt, y), f, axis).get(), out.get(),
                ops.conv_axis_stack(rt, dev(rt, xs), fs, STACK_TERMS, axis + 1).get(),
                ops.conv_axis_stack_bwd(rt, dev(rt, ys), fs, back, axis + 1).get()]
    monkeypatch.setattr(ops, "STAGED_ROWS", True)
    got = run_all()
    if int(np.prod(shape[axis + 1:])) >= conv_run:   # runs within one position: no staging
        assert not any(staged)
    else:
        assert staged[1] and staged[2] and staged[4]   # in the order of run_all's calls
        if shape[axis] > flen:   # the adjoint stages lines longer than the filter
            assert staged[0] and staged[3] and staged[5]
    monkeypatch.setattr(ops, "STAGED_ROWS", False)
    for name, a, b in zip(("forward", "zero border", "adjoint", "accumulate", "stack", "stack adjoint"), got,
                          run_all()):
        np.testing.assert_array_equal(a, b, err_msg=name)


@pytest.mark.parametrize("n, inner, q", [(19, 3, 2), (40, 3, 2), (64, 1, 2), (5, 3, 2), (33, 3, 1)])
@pytest.mark.parametrize("group", [1, 5])
def test_conv_resample_rows_gives_the_two_launches_bits(rt, conv_run, monkeypatch, n, inner, q, group):
    """conv_resample_stack along rows (one launch: conv_resample_rows) gives the bits of
    conv_axis_stack followed by resample_axis, lines shorter than the filter included."""
    monkeypatch.setattr(ops, "rows_group", lambda rt: group)
    f = rand((3, 13), n + q)
    x = rand((3, 4, n, inner), inner + q)
    launches = []
    plain_kernel = rt.kernel
    monkeypatch.setattr(rt, "kernel", lambda *a, **k: launches.append(a[1]) or plain_kernel(*a, **k))
    got = ops.conv_resample_stack(rt, dev(rt, x), f, STACK_TERMS, q, 2).get()
    assert ("conv_resample_rows" in launches) == (inner < conv_run)
    monkeypatch.setattr(ops, "STAGED_ROWS", False)
    np.testing.assert_array_equal(got, ops.conv_resample_stack(rt, dev(rt, x), f, STACK_TERMS, q, 2).get())
    assert got.shape == (len(STACK_TERMS), 4, F.resampled_length(n, q), inner)


@pytest.mark.parametrize("n_in, inner, q", [(19, 3, 2), (40, 3, 2), (64, 1, 2), (9, 3, 2), (33, 3, 1)])
@pytest.mark.parametrize("group", [1, 5])
def test_resample_conv_rows_adjoint_gives_the_two_launches_bits(rt, conv_run, monkeypatch, n_in, inner, q, group):
    """resample_conv_stack_bwd along rows (one launch: resample_conv_rows_bwd) gives the bits of
    resample_axis_bwd followed by conv_axis_stack_bwd, alone and accumulating; lines not longer
    than the filter take the two launches."""
    monkeypatch.setattr(ops, "rows_group", lambda rt: group)
    n_out = F.resampled_length(n_in, q)
    f = rand((3, 13), n_in + q)
    v = rand((3, 4, n_out, inner), inner + q)
    base = rand((len(STACK_TERMS), 4, n_in, inner), 5)

    def both():
        out = ops.resample_conv_stack_bwd(rt, dev(rt, v), q, n_in, f, STACK_TERMS, 2,
                                          out=dev(rt, np.zeros_like(base)))
        acc = ops.resample_conv_stack_bwd(rt, dev(rt, v), q, n_in, f, STACK_TERMS, 2, out=dev(rt, base),
                                          accumulate=True)
        return out.get(), acc.get()
    launches = []
    plain_kernel = rt.kernel
    monkeypatch.setattr(rt, "kernel", lambda *a, **k: launches.append(a[1]) or plain_kernel(*a, **k))
    got = both()
    fused = "resample_conv_rows_bwd" in launches
    assert fused == (inner < conv_run and n_in > 13)
    monkeypatch.setattr(ops, "STAGED_ROWS", False)
    for a, b in zip(got, both()):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("shape, axis", [((3, 5, 7, 3), 2), ((3, 33, 21, 3), 1), ((3, 33, 21, 3), 2),
                                         ((3, 2, 4, 1), 1), ((3, 1, 9, 2), 1), ((3, 70), 1)])
def test_conv_axis_stack_adjoint(rt, conv_run, shape, axis):
    x = rand(shape, 5)
    f = rand((3, 13), 6)
    Ax = ops.conv_axis_stack(rt, dev(rt, x), f, STACK_TERMS, axis).get()
    # the adjoint reads the same terms the other way: input slot s of the forward gathers from the
    # output slots t whose terms use s
    back = tuple(tuple((t, g) for t, terms in enumerate(STACK_TERMS) for s2, g in terms if s2 == s)
                 for s in range(shape[0]))
    y = rand(Ax.shape, 7)
    ATy = ops.conv_axis_stack_bwd(rt, dev(rt, y), f, back, axis).get()
    assert ATy.shape == x.shape
    assert dot(Ax, y) == pytest.approx(dot(x, ATy), rel=1e-4, abs=1e-4)
    # bit for bit the single adjoints added in order, and accumulating adds
    for s, terms in enumerate(back):
        one = [ops.conv_axis_bwd(rt, dev(rt, y[t]), f[g], axis - 1).get() for t, g in terms]
        np.testing.assert_array_equal(ATy[s], sum(one[1:], one[0]))
    out = dev(rt, x)
    ops.conv_axis_stack_bwd(rt, dev(rt, y), f, back, axis, out=out, accumulate=True)
    np.testing.assert_array_equal(out.get(), x + ATy)


def test_conv_axis_stack_refuses_bad_terms(rt):
    x = dev(rt, rand((2, 6, 5), 0))
    f = rand((3, 5), 1)
    for terms in (((),), (((2, 0),),), (((0, 3),),), (((0, -1),),)):
        with pytest.raises(ValueError):
            ops.conv_axis_stack(rt, x, f, terms, 1)
    with pytest.raises(ValueError):
        ops.conv_axis_stack(rt, x, f, (((0, 0),),), 0)        # the slot axis
    with pytest.raises(ValueError):
        ops.conv_axis_stack_bwd(rt, x, f, (((0, 0),),), 1, out=dev(rt, rand((2, 6, 5), 2)))   # out of 1 slot


def test_adjoints_accumulate(rt):
    y, f = rand((6, 5, 2), 5), rand(9, 6)
    base = rand((6, 5, 2), 7)
    out = dev(rt, base)
    ops.conv_axis_bwd(rt, dev(rt, y), f, 1, out=out, accumulate=True)
    np.testing.assert_allclose(out.get(), base + ops.conv_axis_bwd(rt, dev(rt, y), f, 1).get(), atol=1e-5)
    yo = rand((4, 5, 2), 8)
    out = dev(rt, base)
    ops.resample_axis_bwd(rt, dev(rt, yo), 2, 0, 6, out=out, accumulate=True)
    np.testing.assert_allclose(out.get(), base + ops.resample_axis_bwd(rt, dev(rt, yo), 2, 0, 6).get(), atol=1e-5)


@pytest.mark.parametrize("q", [1, 2, 3, 5])
@pytest.mark.parametrize("shape,axis", [((1, 3), 1), ((2, 7), 1), ((11, 4, 3), 0), ((11, 10, 3), 1), ((40, 2), 0),
                                        ((9, 20, 3), 0), ((3, 7, 17), 1), ((13, 3, 9), 1)])
def test_resample_matches_reference_and_adjoint(rt, q, shape, axis):
    # inner < 8 (image rows): the one-position-per-work-item kernels; inner >= 8 (columns): the
    # 8-element runs, in one sample (8-wide loads) or across samples
    x = rand(shape, q)
    got = ops.resample_axis(rt, dev(rt, x), q, axis).get()
    ref = F.resample_axis(x, q, axis)
    assert got.shape == ref.shape
    np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-6)
    y = rand(ref.shape, q + 10)
    ATy = ops.resample_axis_bwd(rt, dev(rt, y), q, axis, shape[axis]).get()
    assert ATy.shape == x.shape
    assert abs(dot(got, y) - dot(x, ATy)) <= 1e-5 * (1 + np.abs(got * y).sum())
    M = F.resample_weights(shape[axis], q)
    ref_t = np.moveaxis(np.tensordot(M.T, np.moveaxis(y.astype(np.float64), axis, 0), axes=(1, 0)), 0, axis)
    np.testing.assert_allclose(ATy, ref_t, rtol=1e-5, atol=1e-6)


def test_a2_resampling_is_plain_dyadic_downsampling(rt):
    x = rand((13, 11, 3), 0)
    down = ops.resample_axis(rt, ops.resample_axis(rt, dev(rt, x), 1, 0), 1, 1).get()
    np.testing.assert_array_equal(down, x[::2, ::2])  # bit-exact: weight 1, nothing interpolated


def test_a2_transform_is_filtering_then_every_second_sample(rt):
    x = rand((13, 11, 3), 1)
    f = F.design_filters(1)
    got = ops.decompose(rt, dev(rt, x), 1, 1)[0]
    for band in BANDS:
        fr, fc = F.BAND_FILTERS[band]
        full = F.conv_axis(F.conv_axis(x, f[fr], 1), f[fc], 0)
        np.testing.assert_allclose(got[band].get(), full[::2, ::2], rtol=1e-5, atol=1e-5)


TRANSFORM_CASES = [((13, 11, 3), 1, 2), ((13, 11, 3), 2, 2), ((20, 31, 1), 3, 2), ((9, 8, 6), 2, 3),
                   ((3, 5, 2), 2, 2), ((1, 1, 1), 1, 2), ((48, 40, 3), 4, 2)]


@pytest.mark.parametrize("shape,q,levels", TRANSFORM_CASES)
def test_decompose_matches_reference(rt, shape, q, levels):
    x = rand(shape, 3)
    got = ops.decompose(rt, dev(rt, x), q, levels)
    ref = F.decompose(x, q, levels)
    assert len(got) == levels
    for j in range(levels):
        for band in BANDS:
            assert got[j][band].shape == ref[j][band].shape
            np.testing.assert_allclose(got[j][band].get(), ref[j][band], rtol=1e-5, atol=2e-6)


@pytest.mark.parametrize("shape,q,levels", TRANSFORM_CASES)
def test_decompose_adjoint_dot_product(rt, shape, q, levels):
    x = rand(shape, 5)
    Ax = [{b: v.get() for b, v in lv.items()} for lv in ops.decompose(rt, dev(rt, x), q, levels)]
    y = [{b: rand(Ax[j][b].shape, 10 * j + i) for i, b in enumerate(BANDS)} for j in range(levels)]
    ATy = ops.decompose_bwd(rt, [{b: dev(rt, y[j][b]) for b in BANDS} for j in range(levels)], shape, q).get()
    assert ATy.shape == x.shape
    lhs = sum(dot(Ax[j][b], y[j][b]) for j in range(levels) for b in BANDS)
    scale = sum(np.abs(Ax[j][b] * y[j][b]).sum() for j in range(levels) for b in BANDS)
    assert abs(lhs - dot(x, ATy)) <= 1e-5 * (1 + scale)


def test_random_sizes_against_reference(rt):
    rng = np.random.default_rng(11)
    for _ in range(small(6, 1)):
        H, W, C = int(rng.integers(1, 40)), int(rng.integers(1, 40)), int(rng.integers(1, 5))
        q = int(rng.integers(1, 6))
        x = rng.random((H, W, C)).astype(np.float32)
        got = ops.decompose(rt, dev(rt, x), q, 2)
        ref = F.decompose(x, q, 2)
        for j in range(2):
            for band in BANDS:
                np.testing.assert_allclose(got[j][band].get(), ref[j][band], rtol=1e-5, atol=2e-6,
                                           err_msg=f"{(H, W, C)} q={q} level {j} {band}")


def test_bad_inputs_are_refused(rt):
    with pytest.raises(ValueError, match="odd"):
        ops.conv_axis(rt, dev(rt, rand((4, 4), 0)), np.ones(4), 0)
    with pytest.raises(TypeError):
        ops.conv_axis(rt, cla.to_device(rt.queue, np.zeros((4, 4))), np.ones(3), 0)
    with pytest.raises(ValueError, match="does not resample"):
        ops.resample_axis_bwd(rt, dev(rt, rand((3,), 0)), 2, 0, 9)
