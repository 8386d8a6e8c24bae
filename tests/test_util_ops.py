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
