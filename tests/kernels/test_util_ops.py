"""Device utilities: the non-finite guard, the step gate, the deferred read-back."""
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


# ------------------------------------------------------------------------------ the step gate
def _gate(rt, skip0, grads_bad, loss_bad, rows=None, pairs=None, supervised=None):
    """step_gate on the device with counts (value, capacity) placed at an offset in a longer array,
    as the binning's offsets [N + 1] hold M at [N]; returns the new gate."""
    import pyopencl.array as cla

    from endowave_cl.ops.binning import PairCount
    from endowave_cl.ops.util import step_gate
    keep = []

    def dev(x):
        a = cla.to_device(rt.queue, np.asarray(x, np.int32))
        keep.append(a)
        return a

    def count(vc):
        if vc is None:
            return None
        value, cap = vc
        offsets = dev([7, 3, 5, value])           # M at [3], as offsets [N + 1] with N = 3
        return PairCount.enqueue_read(rt, offsets, 3, cap, None)
    skip = dev([skip0])
    step_gate(rt, skip, dev([grads_bad]), dev([loss_bad]), rows=count(rows), pairs=count(pairs),
              supervised=None if supervised is None else dev([supervised]))
    return int(skip.get()[0])


@pytest.mark.oclgrind
@pytest.mark.parametrize("case", [
    dict(), dict(grads_bad=1), dict(loss_bad=1), dict(rows=(10, 10)), dict(rows=(11, 10)),
    dict(pairs=(100, 99)), dict(pairs=(0, 1024)), dict(supervised=0), dict(supervised=5),
    dict(skip0=4), dict(skip0=2, rows=(11, 10), pairs=(2000, 1024), grads_bad=1, supervised=0)])
def test_step_gate_matches_reference(rt, case):
    from endowave_cl.reference.util import step_gate_ref
    c = dict(dict(skip0=0, grads_bad=0, loss_bad=0), **case)
    rows, pairs = c.get("rows"), c.get("pairs")
    want = step_gate_ref(c["skip0"], c["grads_bad"], c["loss_bad"],
                         None if rows is None else rows[0], -1 if rows is None else rows[1],
                         None if pairs is None else pairs[0], -1 if pairs is None else pairs[1],
                         c.get("supervised"))
    assert _gate(rt, c["skip0"], c["grads_bad"], c["loss_bad"], rows, pairs, c.get("supervised")) == want


def test_step_gate_leaves_host_known_counts_untested(rt):
    """A count the host knew when it sized the buffer (PairCount(m, m)) is not tested on the device."""
    import pyopencl.array as cla

    from endowave_cl.ops.binning import PairCount
    from endowave_cl.ops.util import step_gate
    z = cla.zeros(rt.queue, (1,), np.int32)
    skip = cla.zeros(rt.queue, (1,), np.int32)
    step_gate(rt, skip, z, z, rows=PairCount(5, 5), pairs=PairCount(0, 0))
    assert int(skip.get()[0]) == 0


def test_pending_read_matches_read_back(rt):
    import pyopencl.array as cla

    from endowave_cl.ops.util import PendingRead, read_back
    rng = np.random.default_rng(1)
    arrays = {"a": cla.to_device(rt.queue, rng.standard_normal((3, 5)).astype(np.float32)),
              "b": cla.to_device(rt.queue, np.arange(7, dtype=np.int32)),
              "empty": cla.zeros(rt.queue, (0,), np.float32)}
    p = PendingRead(rt, arrays)
    arrays["b"].fill(-1)              # enqueued after the read: not in it
    got, now = p.result(), read_back(rt, arrays)
    assert p.done
    np.testing.assert_array_equal(got["a"], arrays["a"].get())
    np.testing.assert_array_equal(got["b"], np.arange(7))
    np.testing.assert_array_equal(now["b"], np.full(7, -1))
    assert got["empty"].shape == (0,)


@pytest.mark.oclgrind
@pytest.mark.parametrize("n", [0, 1, 127, 128, 1000])
def test_average_into_against_its_reference(rt, n):
    """average_into against average_into_ref, in a partly filled last work-group and for an empty
    array; a run of snapshots with w = 1 / k gives their mean."""
    import pyopencl.array as cla

    from endowave_cl.ops.util import average_into
    from endowave_cl.reference.util import average_into_ref
    rng = np.random.default_rng(n)
    snaps = [rng.standard_normal(n).astype(np.float32) * 10 for _ in range(5)]
    avg = cla.to_device(rt.queue, snaps[0])
    want = snaps[0]
    for k, x in enumerate(snaps[1:], start=2):
        average_into(rt, avg, cla.to_device(rt.queue, x), 1.0 / k)
        want = average_into_ref(want, x, 1.0 / k)
    got = avg.get()
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(got, np.mean(snaps, axis=0), rtol=1e-5, atol=1e-5)


def test_average_into_refuses_sizes_that_differ(rt):
    import pyopencl.array as cla

    from endowave_cl.ops.util import average_into
    with pytest.raises(ValueError, match="sizes differ"):
        average_into(rt, cla.zeros(rt.queue, (4,), np.float32), cla.zeros(rt.queue, (5,), np.float32), 0.5)
