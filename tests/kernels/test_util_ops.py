"""Device utilities: the non-finite guard."""
import numpy as np
import pytest


@pytest.mark.oclgrind
@pytest.mark.parametrize("bad", [None, np.nan, np.inf, -np.inf])
def test_any_nonfinite(rt, bad):
    import pyopencl.array as cla

    from endowave_cl.ops.util import any_nonfinite
    a = np.random.default_rng(0).standard_normal(1000).astype(np.float32)
    b = np.zeros((0,), np.float32)
    c = np.ones(129, np.float32)
    if bad is not None:
        c[128] = bad        # the last element, in a partly filled work-group
    arrs = [cla.to_device(rt.queue, x) for x in (a, b, c)]
    assert any_nonfinite(rt, arrs) == (bad is not None)


@pytest.mark.parametrize("pos", [0, 7, 63, 64, 200, 255, 256, 300])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_any_nonfinite_every_position(rt, pos, bad):
    """One bad element anywhere: inside a work-item's full run of 64 or its shorter last run;
    the largest finite floats and denormals are not flagged."""
    import pyopencl.array as cla

    from endowave_cl.ops.util import any_nonfinite
    x = np.random.default_rng(pos).standard_normal(301).astype(np.float32)
    x[::3] = np.finfo(np.float32).max
    x[1::3] = -np.finfo(np.float32).tiny / 4
    assert not any_nonfinite(rt, [cla.to_device(rt.queue, x)])
    x[pos] = bad
    assert any_nonfinite(rt, [cla.to_device(rt.queue, x)])


@pytest.mark.oclgrind
@pytest.mark.parametrize("where", [None, 0, 7, 8, 10])
def test_any_nonfinite_over_many_arrays(rt, where):
    """More arrays than one launch takes (NONFINITE_ARRAYS), of different sizes, empty ones among
    them: a bad element in any one of them, the first, the last of a launch or of the next, is found."""
    import pyopencl.array as cla

    from endowave_cl.ops.util import NONFINITE_ARRAYS, any_nonfinite
    sizes = [300, 5, 0, 64, 1, 129, 0, 700, 3, 65, 2]
    assert len(sizes) > NONFINITE_ARRAYS
    xs = [np.random.default_rng(i).standard_normal(n).astype(np.float32) for i, n in enumerate(sizes)]
    if where is not None:
        xs[where][-1] = np.nan
    assert any_nonfinite(rt, [cla.to_device(rt.queue, x) for x in xs]) == (where is not None)


@pytest.mark.oclgrind
def test_read_back_several_arrays_in_one_read(rt):
    """read_back returns every array as it is on the device: dtypes, shapes, odd byte sizes, an
    offset view, an empty array, and the NaN flag enqueued without a read."""
    import pyopencl.array as cla

    from endowave_cl.ops.util import nonfinite_flag, read_back
    rng = np.random.default_rng(1)
    host = {"f": rng.standard_normal((7, 5)).astype(np.float32), "i": np.arange(3, dtype=np.int32),
            "u": np.arange(5, dtype=np.uint8), "e": np.zeros((0, 2), np.float32)}
    dev = {k: cla.to_device(rt.queue, v) for k, v in host.items()}
    base = cla.to_device(rt.queue, np.arange(10, dtype=np.float32))
    dev["view"] = base[4:]
    bad = cla.to_device(rt.queue, np.array([1.0, np.nan], np.float32))
    dev["flag"] = nonfinite_flag(rt, [dev["f"], bad])
    got = read_back(rt, dev)
    for k, v in host.items():
        assert got[k].dtype == v.dtype and got[k].shape == v.shape
        np.testing.assert_array_equal(got[k], v)
    np.testing.assert_array_equal(got["view"], np.arange(4, 10, dtype=np.float32))
    assert got["flag"].tolist() == [1]
    assert read_back(rt, {"e": dev["e"]})["e"].shape == (0, 2)
