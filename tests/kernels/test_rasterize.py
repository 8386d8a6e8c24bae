"""Tile rasterizer: forward and adjoint kernels vs the torch references, densification statistics."""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pytest

from conftest import small
import endowave_cl.ops.rasterize as RZ
from endowave_cl.ops.rasterize import (ENV_VARIANT, ENV_VEC_BLOCK_W, ENV_VEC_WIDTH, VEC_BWD_BATCHES,
                                       accumulate_densify_stats, fwd_vec_local_bytes, rasterize, rasterize_bwd,
                                       vec_bwd_local_bytes, vec_block)
from endowave_cl.probe import verdict
from endowave_cl.reference.binning import (bin_gaussians_ref, bin_offsets_ref, sort_pairs_ref, tile_grid,
                                           tile_ranges_ref)
from endowave_cl.reference.rasterize import (ALPHA_MAX, accumulate_densify_stats_ref, rasterize_bwd_ref,
                                             rasterize_dense_ref, rasterize_ref)
from endowave_cl.layout import TILE


def make_scene(seed, n, width, height, C=6, sigma=(1.0, 6.0), opac=(0.05, 1.0), margin=8.0):
    """Random screen-space Gaussians plus their sorted list, built with the numpy binning reference.

    sigma: range of the 2D standard deviations in pixels; opac: range of opacities.
    """
    rng = np.random.default_rng(seed)
    means2d = np.stack([rng.uniform(-margin, width + margin, n), rng.uniform(-margin, height + margin, n)], 1)
    s = rng.uniform(*sigma, (n, 2))
    th = rng.uniform(0, np.pi, n)
    R = np.stack([np.stack([np.cos(th), -np.sin(th)], 1), np.stack([np.sin(th), np.cos(th)], 1)], 1)  # [N,2,2]
    cov = R @ (s[:, :, None] ** 2 * np.eye(2)[None]) @ np.transpose(R, (0, 2, 1)) + 0.3 * np.eye(2)[None]
    inv = np.linalg.inv(cov)
    conic = np.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], 1)
    lam = np.linalg.eigvalsh(cov)[:, -1]
    radius = np.ceil(3 * np.sqrt(lam)).astype(np.int32)
    tiles_x, tiles_y = tile_grid(width, height)
    rect = np.stack([np.floor((means2d[:, 0] - radius) / TILE), np.floor((means2d[:, 1] - radius) / TILE),
                     np.ceil((means2d[:, 0] + radius) / TILE), np.ceil((means2d[:, 1] + radius) / TILE)], 1)
    rect = np.clip(rect, 0, [tiles_x, tiles_y, tiles_x, tiles_y]).astype(np.int32)
    empty = (rect[:, 2] <= rect[:, 0]) | (rect[:, 3] <= rect[:, 1])
    radius[empty] = 0
    rect[empty] = 0
    sc = dict(means2d=means2d.astype(np.float32), conic=conic.astype(np.float32),
              opac=rng.uniform(*opac, n).astype(np.float32),
              features=rng.uniform(-1, 1, (n, C)).astype(np.float32),
              depth=rng.uniform(0.5, 5.0, n).astype(np.float32), radius=radius, rect=rect,
              width=width, height=height)
    return with_sorted_list(sc)


def with_sorted_list(sc):
    tiles_x, tiles_y = tile_grid(sc["width"], sc["height"])
    keys, vals = bin_gaussians_ref(sc["rect"], sc["depth"], sc["radius"], tiles_x)
    skeys, svals = sort_pairs_ref(keys, vals)
    sc["sorted_values"] = svals.astype(np.int32)
    sc["tile_ranges"] = tile_ranges_ref(skeys, tiles_x * tiles_y)
    return sc


def to_dev(rt, sc):
    names = ("means2d", "conic", "opac", "features", "sorted_values", "tile_ranges")
    return [cla.to_device(rt.queue, np.ascontiguousarray(sc[n])) for n in names]


def run_fwd(rt, sc):
    dev = to_dev(rt, sc)
    r = rasterize(rt, *dev, sc["width"], sc["height"])
    return dev, r


def ref_fwd(sc):
    return rasterize_ref(sc["means2d"], sc["conic"], sc["opac"], sc["features"], sc["sorted_values"],
                         sc["tile_ranges"], sc["width"], sc["height"])


def check_fwd(r, ref, atol=1e-4, rtol=1e-4):
    out, alpha, T, last = (x.detach().numpy() for x in ref)
    np.testing.assert_allclose(r.out.get(), out, rtol=rtol, atol=atol)
    np.testing.assert_allclose(r.alpha.get(), alpha, rtol=rtol, atol=atol)
    np.testing.assert_allclose(r.T_final.get(), T, rtol=rtol, atol=atol)
    np.testing.assert_array_equal(r.last.get(), last)
    for x in (r.out.get(), r.alpha.get(), r.T_final.get()):
        assert np.isfinite(x).all()


# ------------------------------------------------------------------------------------------ forward
def require_builds(rt, vw, bw, C=6):
    """Skip when the vector variant does not build on this device (its probe, in a child process,
    aborted, hung or failed to compile); fail when it builds but computes wrong values."""
    if rt.is_oclgrind:
        return
    v = verdict(rt, C, vw, bw)
    if v.ok:
        return
    if v.kind == "wrong":
        pytest.fail(f"vector rasterizer at {vw} lanes ({bw}-wide blocks) computes wrong values: {v.reason}")
    pytest.skip(f"vector rasterizer at {vw} lanes does not build on {rt.name}: {v.reason}")


def skip_unless_fits(rt, variant, C):
    """Skip a vector variant whose kernels need more local memory than the device has (Oclgrind has
    32 KiB: the 4-lane adjoint with 9 channels does not fit; raster_choice never picks it there)."""
    if variant.startswith("vector"):
        vw = int(variant[6:])
        need = max(fwd_vec_local_bytes(C), vec_bwd_local_bytes(C, VEC_BWD_BATCHES[-1], vw))
        if need > rt.local_mem_size:
            pytest.skip(f"{variant} with C={C} needs {need} bytes of local memory, {rt.name} has {rt.local_mem_size}")


# Every variant: the scalar kernels (the GPU path) and the vector ones at each lane count (CPU
# drivers; the default picks the fastest that passes its probe).
VARIANT_PARAMS = ["scalar", "vector4", "vector8", "vector16"]


@pytest.fixture(params=VARIANT_PARAMS)
def variant(request, monkeypatch, rt):
    """Run the test with each rasterizer variant, forward and adjoint."""
    name = request.param
    monkeypatch.setenv(ENV_VARIANT, name[:6])
    if name.startswith("vector"):
        vw = int(name[6:])
        monkeypatch.setenv(ENV_VEC_WIDTH, str(vw))
        require_builds(rt, vw, vec_block(vw)[0])
    return name


FWD_CASES = [
    # seed, n, width, height, C, sigma, opac
    (0, 60, 45, 37, 6, (1.0, 6.0), (0.05, 1.0)),       # not multiples of 16
    (1, 200, 64, 48, 6, (1.0, 4.0), (0.5, 1.0)),       # dense: clamped alphas, saturated pixels
    (2, 40, 33, 50, 1, (2.0, 10.0), (0.05, 0.9)),      # C = 1
    (3, 80, 50, 29, 9, (0.5, 3.0), (0.1, 1.0)),        # C = 9, small footprints
]


@pytest.mark.parametrize("case", FWD_CASES)
def test_forward_matches_references(rt, variant, case):
    seed, n, w, h, C, sigma, op = case
    sc = make_scene(seed, n, w, h, C, sigma, op)
    _, r = run_fwd(rt, sc)
    check_fwd(r, ref_fwd(sc))
    dense = rasterize_dense_ref(sc["means2d"], sc["conic"], sc["opac"], sc["features"], sc["depth"],
                                sc["rect"], w, h)
    check_fwd(r, dense)


def test_forward_saturates_and_clamps(rt, variant):
    """Opaque, wide Gaussians: alphas hit ALPHA_MAX and pixels stop early (T < 1e-4)."""
    sc = make_scene(5, 150, 40, 40, 6, (4.0, 12.0), (0.995, 1.0))
    raw = sc["opac"]
    assert (raw > ALPHA_MAX).all()
    _, r = run_fwd(rt, sc)
    ref = ref_fwd(sc)
    check_fwd(r, ref)
    T = r.T_final.get()
    # many pixels stopped: their T stayed >= T_STOP but their list goes on past `last`
    assert (T < 1e-2).mean() > 0.5
    assert T.min() >= 1e-4 * (1 - 1e-6)
    ranges = sc["tile_ranges"]
    tiles_x, _ = tile_grid(40, 40)
    lens = np.array([[ranges[(y // 16) * tiles_x + x // 16, 1] - ranges[(y // 16) * tiles_x + x // 16, 0]
                      for x in range(40)] for y in range(40)])
    assert (r.last.get() < lens).mean() > 0.5


def test_forward_empty_scene(rt, variant):
    sc = make_scene(0, 0, 45, 37, 6)
    assert len(sc["sorted_values"]) == 0
    _, r = run_fwd(rt, sc)
    assert np.all(r.out.get() == 0) and np.all(r.alpha.get() == 0) and np.all(r.T_final.get() == 1)
    assert np.all(r.last.get() == 0)


def test_forward_one_gaussian_many_tiles(rt, variant):
    """A single wide Gaussian covering every tile of a 70 x 52 image."""
    w, h = 70, 52
    sc = make_scene(0, 1, w, h, 3)
    sc["means2d"][:] = [[35.2, 26.7]]
    sc["conic"][:] = [[1 / 400.0, 1 / 2000.0, 1 / 300.0]]
    sc["opac"][:] = [0.8]
    sc["radius"][:] = [60]
    tx, ty = tile_grid(w, h)
    sc["rect"][:] = [[0, 0, tx, ty]]
    sc = with_sorted_list(sc)
    assert len(sc["sorted_values"]) == tx * ty
    _, r = run_fwd(rt, sc)
    check_fwd(r, ref_fwd(sc))
    assert (r.last.get() == 1).mean() > 0.9


def test_forward_many_batches(rt, variant):
    """More than 256 Gaussians in one tile (several local-memory batches), faint so no pixel stops."""
    sc = make_scene(7, small(700, 300), 20, 18, 6, (3.0, 8.0), (0.01, 0.05))
    _, r = run_fwd(rt, sc)
    ranges = sc["tile_ranges"]
    assert (ranges[:, 1] - ranges[:, 0]).max() > 512
    check_fwd(r, ref_fwd(sc))


def test_indefinite_conics_are_not_culled_wrongly(rt, variant):
    """Conics that are not positive definite get no cull box: same result as the references."""
    sc = make_scene(8, 60, 45, 37, 6, (1.0, 4.0), (0.2, 1.0))
    sc["conic"][::3, 1] = 2.0 * np.sqrt(sc["conic"][::3, 0] * sc["conic"][::3, 2])   # det < 0
    _, r = run_fwd(rt, sc)
    check_fwd(r, ref_fwd(sc))
    got, ref = run_bwd(rt, sc)
    check_bwd(got, ref)


@pytest.mark.oclgrind
def test_forward_tiny_oclgrind(rt, variant):
    sc = make_scene(11, 12, 20, 18, 6, (1.0, 5.0), (0.3, 1.0))
    _, r = run_fwd(rt, sc)
    check_fwd(r, ref_fwd(sc))


@pytest.mark.oclgrind
def test_forward_vector_saturated_tiny_oclgrind(rt, monkeypatch):
    """The vector variant with lanes stopping at different Gaussians and a partial last run."""
    monkeypatch.setenv(ENV_VARIANT, "vector")
    sc = make_scene(15, 14, 21, 18, 2, (2.0, 6.0), (0.9, 1.0))
    _, r = run_fwd(rt, sc)
    check_fwd(r, ref_fwd(sc))


# (lanes, block width) of the vector variant other than the default (VEC_WIDTH, VEC_BLOCK_W)
VEC_SHAPES = [(4, 4), (8, 4), (8, 8), (16, 8), (16, 16)]


def vector_shape_scene(rt, monkeypatch, vw, bw, case):
    """Select the vector variant at vw lanes and block width bw (skipped where it does not build)
    and make the scene of case (seed, n, w, h, C, sigma range, opacity range)."""
    monkeypatch.setenv(ENV_VARIANT, "vector")
    monkeypatch.setenv(ENV_VEC_WIDTH, str(vw))
    monkeypatch.setenv(ENV_VEC_BLOCK_W, str(bw))
    require_builds(rt, vw, bw)
    return make_scene(*case)


@pytest.mark.parametrize("vw,bw", VEC_SHAPES)
@pytest.mark.parametrize("case", [FWD_CASES[0], FWD_CASES[1]])
def test_forward_vector_widths(rt, monkeypatch, vw, bw, case):
    """Other lane counts and pixel-block shapes of the vector variant."""
    sc = vector_shape_scene(rt, monkeypatch, vw, bw, case)
    _, r = run_fwd(rt, sc)
    check_fwd(r, ref_fwd(sc))


# ------------------------------------------------------------------------------------------ adjoint
def run_bwd(rt, sc, seed=0, deterministic=False):
    dev, r = run_fwd(rt, sc)
    w, h, C = sc["width"], sc["height"], sc["features"].shape[1]
    rng = np.random.default_rng(100 + seed)
    v_out = rng.standard_normal((h, w, C)).astype(np.float32)
    v_alpha = rng.standard_normal((h, w)).astype(np.float32)
    det = None
    if deterministic:
        det = (cla.to_device(rt.queue, np.ascontiguousarray(sc["rect"], np.int32)),
               cla.to_device(rt.queue, bin_offsets_ref(sc["rect"], sc["radius"])))
    g = rasterize_bwd(rt, *dev, w, h, r, cla.to_device(rt.queue, v_out), cla.to_device(rt.queue, v_alpha),
                      deterministic=det)
    ref = rasterize_bwd_ref(sc["means2d"], sc["conic"], sc["opac"], sc["features"], sc["sorted_values"],
                            sc["tile_ranges"], w, h, v_out, v_alpha)
    return {k: v.get() for k, v in g.items()}, ref


def check_bwd(got, ref, rtol=2e-3):
    """Per-output tolerance relative to the output's magnitude (float32, division-recovered T)."""
    for name in ("v_means2d", "v_conic", "v_opac", "v_features"):
        a, b = got[name], ref[name]
        assert a.shape == b.shape and np.isfinite(a).all(), name
        scale = max(np.abs(b).max(), 1e-6)
        np.testing.assert_allclose(a, b, rtol=rtol, atol=rtol * scale, err_msg=name)


BWD_CASES = [
    (0, 60, 45, 37, 6, (1.0, 6.0), (0.05, 1.0)),
    (1, 120, 40, 40, 6, (2.0, 6.0), (0.6, 1.0)),    # clamped alphas and saturated pixels
    (2, 40, 33, 50, 1, (2.0, 10.0), (0.05, 0.9)),
    (3, 80, 50, 29, 9, (0.5, 3.0), (0.1, 1.0)),
    (4, 300, 20, 18, 6, (3.0, 8.0), (0.01, 0.1)),    # several batches per tile
]


@pytest.mark.parametrize("vw,bw", VEC_SHAPES)
@pytest.mark.parametrize("case", [BWD_CASES[1], BWD_CASES[4]])
def test_adjoint_vector_widths(rt, monkeypatch, vw, bw, case):
    """Other lane counts and pixel-block shapes of the vector variant, both reduction modes."""
    sc = vector_shape_scene(rt, monkeypatch, vw, bw, case)
    for det in (False, True):
        got, ref = run_bwd(rt, sc, case[0], deterministic=det)
        check_bwd(got, ref)


def test_adjoint_vector_batches_same_bits(rt, monkeypatch):
    """The vector adjoint gives the same bits with every batch size it can pick (its hit and
    written-slot masks are 32-bit words up to 32 entries, 64-bit above) in the deterministic mode,
    and the same values to rounding with atomic adds (whose order varies between runs)."""
    monkeypatch.setenv(ENV_VARIANT, "vector")
    monkeypatch.setenv(ENV_VEC_WIDTH, "16")
    require_builds(rt, 16, vec_block(16)[0])
    sc = make_scene(*BWD_CASES[4])   # several batches per tile
    batches = tuple(RZ.VEC_BWD_BATCHES)
    assert max(batches) > 32 >= min(batches)   # both kinds of mask
    for det in (True, False):
        outs = []
        for batch in batches:
            if RZ.vec_bwd_local_bytes(sc["features"].shape[1], batch, 16) > rt.local_mem_size:
                continue
            monkeypatch.setattr(RZ, "VEC_BWD_BATCHES", (batch,))
            outs.append((batch, run_bwd(rt, sc, 4, deterministic=det)[0]))
        assert len(outs) >= 2
        for batch, got in outs[1:]:
            for name, a in got.items():
                b = outs[0][1][name]
                if det:
                    assert np.array_equal(a.view(np.uint32), b.view(np.uint32)), (batch, name)
                else:
                    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6 * max(np.abs(b).max(), 1e-6),
                                               err_msg=f"{batch} {name}")


@pytest.mark.parametrize("case", BWD_CASES)
def test_adjoint_matches_autograd(rt, variant, case):
    seed, n, w, h, C, sigma, op = case
    sc = make_scene(seed, n, w, h, C, sigma, op)
    got, ref = run_bwd(rt, sc, seed)
    check_bwd(got, ref)


def test_adjoint_clamp_blocks_gradient(rt, variant):
    """One Gaussian with opac * G > ALPHA_MAX over every pixel it touches: no gradient to opac or conic."""
    w, h = 20, 18
    sc = make_scene(0, 1, w, h, 2)
    sc["means2d"][:] = [[10.0, 9.0]]
    sc["conic"][:] = [[1e-6, 0.0, 1e-6]]
    sc["opac"][:] = [1.0]
    sc["radius"][:] = [30]
    sc["rect"][:] = [[0, 0, 2, 2]]
    sc = with_sorted_list(sc)
    got, ref = run_bwd(rt, sc)
    assert np.all(got["v_opac"] == 0) and np.all(got["v_conic"] == 0) and np.all(got["v_means2d"] == 0)
    assert np.abs(got["v_features"]).max() > 0
    check_bwd(got, ref)


def test_adjoint_no_lost_update(rt, variant):
    """Every pixel of many tiles hits the same few Gaussians: the CAS sums must equal the reference."""
    w, h = small(96, 32), small(80, 32)
    n = 3
    sc = make_scene(1, n, w, h, 6)
    sc["means2d"][:] = [[w / 2, h / 2], [w / 3, h / 2], [w / 2, h / 3]]
    sc["conic"][:] = [[1 / 900.0, 0.0, 1 / 900.0]] * n
    sc["opac"][:] = [0.3, 0.2, 0.25]
    tx, ty = tile_grid(w, h)
    sc["radius"][:] = 90
    sc["rect"][:] = [[0, 0, tx, ty]] * n
    sc = with_sorted_list(sc)
    dev, r = run_fwd(rt, sc)
    C = 6
    v_out = np.ones((h, w, C), np.float32)
    v_alpha = np.zeros((h, w), np.float32)
    g = rasterize_bwd(rt, *dev, w, h, r, cla.to_device(rt.queue, v_out), cla.to_device(rt.queue, v_alpha))
    # d out / d f_kc summed over pixels = sum_p alpha_k T_k: compare to the reference, per Gaussian
    ref = rasterize_bwd_ref(sc["means2d"], sc["conic"], sc["opac"], sc["features"], sc["sorted_values"],
                            sc["tile_ranges"], w, h, v_out, v_alpha)
    np.testing.assert_allclose(g["v_features"].get(), ref["v_features"], rtol=1e-4)
    np.testing.assert_allclose(g["v_opac"].get(), ref["v_opac"], rtol=1e-3, atol=1e-3)
    # and the per-pixel weights summed directly from the forward outputs (independent of autograd)
    wsum = ref["v_features"][:, 0]
    assert np.all(wsum > 10.0)


def test_adjoint_empty_scene(rt, variant):
    sc = make_scene(0, 0, 45, 37, 6)
    got, ref = run_bwd(rt, sc)
    for k in got:
        assert got[k].shape[0] == 0


@pytest.mark.oclgrind
def test_adjoint_tiny_oclgrind(rt, variant):
    sc = make_scene(12, 12, 20, 18, 6, (1.0, 5.0), (0.3, 1.0))
    got, ref = run_bwd(rt, sc)
    check_bwd(got, ref)


@pytest.mark.oclgrind
def test_adjoint_saturated_tiny_oclgrind(rt, variant):
    sc = make_scene(13, 14, 20, 18, 2, (2.0, 6.0), (0.9, 1.0))
    got, ref = run_bwd(rt, sc)
    check_bwd(got, ref)


@pytest.mark.parametrize("case", [BWD_CASES[0], BWD_CASES[4]])
def test_adjoint_deterministic_mode(rt, variant, case):
    """Bit-identical gradients over runs, equal to the reference like the default mode."""
    seed, n, w, h, C, sigma, op = case
    sc = make_scene(seed, n, w, h, C, sigma, op)
    # equal depths too, so the gather's tie-break on the Gaussian id is exercised
    sc["depth"][: n // 2] = 1.5
    sc = with_sorted_list(sc)
    runs = [run_bwd(rt, sc, seed, deterministic=True) for _ in range(3)]
    for got, _ in runs[1:]:
        for k in got:
            assert np.array_equal(got[k], runs[0][0][k]), k
    check_bwd(runs[0][0], runs[0][1])
    default, _ = run_bwd(rt, sc, seed)
    check_bwd(runs[0][0], default, rtol=1e-4)


def test_adjoint_deterministic_one_gaussian_many_tiles(rt, variant):
    w, h = 70, 52
    sc = make_scene(0, 2, w, h, 3)
    sc["means2d"][:] = [[35.2, 26.7], [20.0, 30.0]]
    sc["conic"][:] = [[1 / 400.0, 1 / 2000.0, 1 / 300.0], [0.05, 0.0, 0.05]]
    sc["opac"][:] = [0.8, 0.5]
    tx, ty = tile_grid(w, h)
    sc["radius"][:] = [60, 0]   # the second one is culled: in no tile, zero gradient
    sc["rect"][:] = [[0, 0, tx, ty], [0, 0, 3, 3]]
    sc = with_sorted_list(sc)
    got, ref = run_bwd(rt, sc, deterministic=True)
    check_bwd(got, ref)
    assert all(np.all(got[k][1] == 0) for k in got)


@pytest.mark.parametrize("case", [BWD_CASES[1], (6, 150, 40, 40, 6, (4.0, 12.0), (0.995, 1.0))])
def test_adjoint_deterministic_rows_past_the_walk(rt, variant, case):
    """Saturated pixels stop before their tile's list ends, so tiles hold entries past the walk
    (past the largest `last`): the vector adjoint writes their per-entry rows as zeros itself (its
    v_entry is not filled first), the scalar one gets a zero-filled array.  The memory pool's
    blocks are poisoned with NaN first, so a row left unwritten would show."""
    seed, n, w, h, C, sigma, op = case
    sc = make_scene(seed, n, w, h, C, sigma, op)
    _, r = run_fwd(rt, sc)
    ranges = sc["tile_ranges"]
    tiles_x, _ = tile_grid(w, h)
    last = r.last.get()
    walked = np.zeros(len(ranges), np.int64)
    for y in range(h):
        for x in range(w):
            t = (y // 16) * tiles_x + x // 16
            walked[t] = max(walked[t], last[y, x])
    assert ((ranges[:, 1] - ranges[:, 0]) > walked).any()   # some tile has entries past its walk
    M = int(ranges[:, 1].max())
    for _ in range(3):   # poison what the pool will hand out for v_entry [M, 6 + C]
        junk = cla.empty(rt.queue, (M, 6 + C), np.float32, allocator=rt.pool())
        junk.fill(np.float32(np.nan))
        rt.queue.finish()
        del junk
    got, ref = run_bwd(rt, sc, seed, deterministic=True)
    check_bwd(got, ref)   # finite, and the reference's values


@pytest.mark.oclgrind
def test_adjoint_deterministic_tiny_oclgrind(rt, variant):
    skip_unless_fits(rt, variant, 9)
    sc = make_scene(14, 12, 20, 18, 9, (1.0, 5.0), (0.3, 1.0))
    got, ref = run_bwd(rt, sc, deterministic=True)
    check_bwd(got, ref)


def test_local_memory_limit_is_reported(rt, variant):
    sc = make_scene(0, 3, 20, 18, 1)
    sc["features"] = np.zeros((3, 4096), np.float32)
    with pytest.raises(ValueError, match="local memory"):
        run_fwd(rt, sc)


# -------------------------------------------------------------------------------------- densify stats
@pytest.mark.parametrize("n", [0, 1, 37, 300])
def test_densify_stats(rt, n):
    rng = np.random.default_rng(n)
    w, h = 640, 512
    v = rng.standard_normal((n, 2)).astype(np.float32) * 1e-3
    radius = rng.integers(-1, 20, n).astype(np.int32)
    radius[::3] = 0
    ga = rng.uniform(0, 1, n).astype(np.float32)
    cnt = rng.integers(0, 5, n).astype(np.int32)
    mr = rng.uniform(0, 15, n).astype(np.float32)
    q = rt.queue
    d_ga, d_cnt, d_mr = (cla.to_device(q, x) for x in (ga, cnt, mr))
    for _ in range(2):  # twice: the stats accumulate
        accumulate_densify_stats(rt, cla.to_device(q, v), cla.to_device(q, radius), w, h, d_ga, d_cnt, d_mr)
        ga, cnt, mr = accumulate_densify_stats_ref(v, radius, w, h, ga, cnt, mr)
    np.testing.assert_allclose(d_ga.get(), ga, rtol=1e-6)
    np.testing.assert_array_equal(d_cnt.get(), cnt)
    np.testing.assert_array_equal(d_mr.get(), mr)
    # gated (the step gate, ops/util.py step_gate): set, nothing changes; 0, the same as ungated
    before = d_ga.get(), d_cnt.get(), d_mr.get()
    for skip in (1, 0):
        accumulate_densify_stats(rt, cla.to_device(q, v), cla.to_device(q, radius), w, h, d_ga, d_cnt, d_mr,
                                 skip=cla.to_device(q, np.array([skip], np.int32)))
    ga, cnt, mr = accumulate_densify_stats_ref(v, radius, w, h, *before)
    np.testing.assert_allclose(d_ga.get(), ga, rtol=1e-6)
    np.testing.assert_array_equal(d_cnt.get(), cnt)
    np.testing.assert_array_equal(d_mr.get(), mr)
