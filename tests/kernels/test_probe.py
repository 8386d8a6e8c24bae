"""Probing the vector rasterizer in a child process: a variant whose build aborts, hangs, fails or
computes wrong values leads to the next one with one line on stderr, never to a dead test process."""
from __future__ import annotations

import numpy as np
import pytest

from endowave_cl import probe as P
from endowave_cl.ops import rasterize as RZ
from endowave_cl.runtime import ENV_CACHE_DIR, Runtime, list_devices

pytestmark = pytest.mark.filterwarnings("ignore:Non-empty compiler output")


@pytest.fixture
def cpu_rt(rt):
    if rt.is_oclgrind or rt.is_gpu:
        pytest.skip("the probe runs for CPU devices")
    return rt


@pytest.fixture
def fresh(monkeypatch, tmp_path):
    """An empty cache folder, no remembered verdicts and no forced variant."""
    monkeypatch.setenv(ENV_CACHE_DIR, str(tmp_path))
    monkeypatch.setattr(P, "_MEMO", {})
    for v in (RZ.ENV_VARIANT, RZ.ENV_VEC_WIDTH, RZ.ENV_VEC_BLOCK_W, P.ENV_PLANT, P.ENV_TIMEOUT):
        monkeypatch.delenv(v, raising=False)
    return tmp_path


def _scene_matches_reference(rt, choice):
    from test_rasterize import make_scene, ref_fwd, to_dev, check_fwd
    sc = make_scene(0, 60, 45, 37, 6)
    r = RZ.rasterize(rt, *to_dev(rt, sc), sc["width"], sc["height"], choice=choice)
    check_fwd(r, ref_fwd(sc))


def test_abort_hang_and_build_failure_fall_back_to_scalar(cpu_rt, fresh, monkeypatch, capfd):
    monkeypatch.setenv(P.ENV_PLANT, "16=abort,8=hang,4=build")
    monkeypatch.setenv(P.ENV_TIMEOUT, "4")
    ch = RZ.raster_choice(cpu_rt, 6)
    assert ch == RZ.RasterChoice("scalar")
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1, err                                          # one line
    line = err[0]
    assert "scalar kernel" in line
    assert "16 lanes: the driver killed the process (SIGABRT)" in line
    assert "8 lanes: no answer within 4 s" in line
    assert "4 lanes: build failed" in line
    kinds = {w: P.verdict(cpu_rt, 6, w, RZ.vec_block(w)[0]).kind for w in (16, 8, 4)}
    assert kinds == {16: "crash", 8: "hang", 4: "build"}
    assert len(list((fresh / "probes").glob("raster-*.json"))) == 3  # verdicts cached
    _scene_matches_reference(cpu_rt, ch)                               # and this process lives on


def test_wrong_values_fall_back_to_8_lanes(cpu_rt, fresh, monkeypatch, capfd):
    """A variant that builds and runs but differs from the scalar kernel is not used."""
    monkeypatch.setenv(P.ENV_PLANT, "16=wrong")
    ch = RZ.raster_choice(cpu_rt, 6)
    assert ch == RZ.RasterChoice("vector", 8, 4)
    line, = capfd.readouterr().err.strip().splitlines()
    assert "vector kernel, 8 lanes" in line and "16 lanes: out differs from the scalar kernel" in line
    assert P.verdict(cpu_rt, 6, 16, 4).kind == "wrong"
    _scene_matches_reference(cpu_rt, ch)


def test_forced_variant_that_fails_is_a_one_line_error(cpu_rt, fresh, monkeypatch):
    monkeypatch.setenv(P.ENV_PLANT, "16=build")
    monkeypatch.setenv(RZ.ENV_VEC_WIDTH, "16")
    with pytest.raises(RZ.RasterVariantError, match="16 lanes: build failed") as ei:
        RZ.raster_choice(cpu_rt, 6)
    assert "\n" not in str(ei.value)
    monkeypatch.setenv(RZ.ENV_VARIANT, "scalar")        # forcing the scalar kernel needs no probe
    assert RZ.raster_choice(cpu_rt, 6) == RZ.RasterChoice("scalar")


def test_warm_start_runs_no_child(cpu_rt, fresh, monkeypatch):
    first = P.verdict(cpu_rt, 6, 16, 4)
    assert first.ok and not first.cached, first
    P._MEMO.clear()                                     # as a new process would start

    def no_child(*a, **k):
        raise AssertionError("probed again")
    monkeypatch.setattr(P, "run_child", no_child)
    again = P.verdict(cpu_rt, 6, 16, 4)
    assert again.ok and again.cached
    # a different driver version, option or kernel source is another key: probed again
    with pytest.raises(AssertionError, match="probed again"):
        P.verdict(cpu_rt, 7, 16, 4)


def test_unreadable_verdict_is_probed_again(cpu_rt, fresh, monkeypatch):
    monkeypatch.setenv(P.ENV_PLANT, "16=build")
    P.verdict(cpu_rt, 6, 16, 4)
    (f,) = (fresh / "probes").glob("raster-*.json")
    f.write_text("{not json")
    P._MEMO.clear()
    v = P.verdict(cpu_rt, 6, 16, 4)
    assert not v.cached and v.kind == "build"


def test_oclgrind_is_not_probed(monkeypatch, fresh):
    entries = [e for e in list_devices() if e.is_oclgrind]
    if not entries:
        pytest.skip("no Oclgrind device")
    rt = Runtime(entries[0], disk_cache=False)

    def no_probe(*a, **k):
        raise AssertionError("probed the simulator")
    monkeypatch.setattr(P, "verdict", no_probe)
    assert RZ.raster_choice(rt, 6) == RZ.RasterChoice("vector", RZ.VEC_WIDTH, 4)


def test_devices_command_shows_the_rasterizer_verdicts(cpu_rt, fresh, capsys):
    from endowave_cl.cli import main
    assert main(["--device", f"{cpu_rt.entry.index}", "devices"]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    star = next(i for i, ln in enumerate(lines) if ln.startswith("*"))
    line = lines[star + 1]                              # the chosen device's rasterizer line
    assert "vector kernel, 16 lanes" in line and "16 lanes ok" in line, out


def test_tiny_scene_has_work_for_every_lane():
    """The probe's scene covers partial tiles and crowded pixels, so wrong lanes show."""
    from endowave_cl.probe_child import _tiny_scene
    arrays, w, h, *_ = _tiny_scene(3)
    assert w % 16 and h % 16
    ranges = arrays["tile_ranges"]
    assert ((ranges[:, 1] - ranges[:, 0]) >= 3).all()
    assert np.isfinite(arrays["conic"]).all()


def test_variants_too_big_for_local_memory_are_skipped(fresh, monkeypatch, capfd):
    """A device with little local memory: lane counts whose kernels do not fit are passed over
    without a probe, and the line says why (fewer lanes need more: more work-items per tile)."""
    need = {w: max(RZ.vec_bwd_local_bytes(6, RZ.VEC_BWD_BATCHES[-1], w), RZ.fwd_vec_local_bytes(6))
            for w in (16, 8, 4)}
    assert need[16] <= need[8] < need[4]

    class Small:
        name, is_gpu, is_oclgrind = "small device", False, False
        local_mem_size = need[8]   # 16 and 8 lanes just fit, 4 do not

        def __init__(self):
            self.cache = {}   # the Runtime's per-device cache (raster_choice keeps its choice there)
    probed = []

    def fake_verdict(rt, C, vw, bw):
        probed.append(vw)
        return P.Verdict(False, "planted failure", 0.0, "build")
    monkeypatch.setattr(P, "verdict", fake_verdict)
    ch = RZ.raster_choice(Small(), 6)
    assert ch == RZ.RasterChoice("scalar") and probed == [16, 8]
    line, = capfd.readouterr().err.strip().splitlines()
    assert "16 lanes: planted failure" in line and "8 lanes: planted failure" in line
    assert f"4 lanes: needs {need[4]} bytes of local memory" in line
