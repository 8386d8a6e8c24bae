"""benchmarks/bench_train_loop.py runs on the tiny scene and prints what it promises: the machine,
the load, the sizes, and per kind of step its wall, kernel and host time, launches and reads, for
the in-between targets built on the device and on the host."""
from __future__ import annotations

from conftest import BENCHMARKS, load_tool


def test_bench_train_loop_runs(capsys, rt, tiny_scene):
    bench = load_tool("bench_train_loop", BENCHMARKS)
    assert bench.main(["--scene", str(tiny_scene), "--downscale", "1", "--steps", "3", "--warmup", "1",
                       "--early", "10", "--late", "3100", "--both-paths"]) == 0
    out = capsys.readouterr().out
    assert "machine:" in out and "load average" in out and "64x48" in out
    for where in ("device", "host"):
        assert f"in-between targets built on the {where}: median per step" in out
    assert "plain" in out and "wall ms" in out and "reads" in out


def test_bench_train_loop_without_the_scene(capsys, tmp_path):
    assert load_tool("bench_train_loop", BENCHMARKS).main(["--scene", str(tmp_path)]) == 0
    assert "nothing timed" in capsys.readouterr().out
