"""Smoke tests of the wavelet tools (tiny settings): tools/compare_wavelets.py and
benchmarks/bench_wavelet.py run and print what they promise."""
from __future__ import annotations

import pytest

from conftest import BENCHMARKS, load_tool as load, oclgrind_active


pytestmark = pytest.mark.skipif(oclgrind_active(), reason="full-size tool runs are too slow on Oclgrind")


def test_compare_wavelets_synthetic(tmp_path, capsys, rt):
    pytest.importorskip("pywt")
    out = tmp_path / "cmp.png"
    load("compare_wavelets").main(["--out", str(out)])
    text = capsys.readouterr().out
    assert out.is_file() and out.stat().st_size > 10000
    for name in ("rational a=3/2", "haar", "bior6.8", "highlight layer", "detail %"):
        assert name in text


def test_compare_wavelets_numpy_matches_opencl(tmp_path, capsys, rt):
    pytest.importorskip("pywt")
    mod = load("compare_wavelets")
    mod.main(["--out", str(tmp_path / "a.png"), "--q", "3"])
    a = capsys.readouterr().out
    mod.main(["--out", str(tmp_path / "b.png"), "--q", "3", "--numpy"])
    b = capsys.readouterr().out
    # same energy tables to the printed precision (float32 kernels vs float64 reference)
    rows = lambda s: [ln for ln in s.splitlines() if ln.startswith("rational")]
    assert rows(a) == rows(b) and len(rows(a)) == 2


def test_bench_wavelet_runs(capsys, rt):
    load("bench_wavelet", BENCHMARKS).main(["--height", "20", "--width", "24", "--runs", "1", "--warmup", "0"])
    text = capsys.readouterr().out
    assert "opencl  transform" in text and "torch   loss + gradient" in text and "20x24x3" in text
