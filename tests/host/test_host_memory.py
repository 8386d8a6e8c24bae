"""host_memory.keep_freed_memory: large host temporaries come back from the heap instead of fresh
mmap'd pages (the page faults it removes are what made the in-between target's host splats slow)."""
import subprocess
import sys
import textwrap

import pytest

from endowave_cl.host_memory import keep_freed_memory

PROBE = textwrap.dedent("""
    import resource, sys
    import numpy as np
    sys.path.insert(0, {root!r})
    if {keep}:
        from endowave_cl.host_memory import keep_freed_memory
        assert keep_freed_memory()
    def faults():
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    def step():
        # four 4 MiB arrays alive at once, every page written, then all freed: glibc's default
        # policy returns the freed top of the heap to the kernel (it exceeds the trim threshold)
        a = [np.ones(1 << 19) for _ in range(4)]
        del a
    step()
    before = faults()
    for _ in range(20):
        step()
    print(faults() - before)
""")


def _faults(keep: bool) -> int:
    import os
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    out = subprocess.run([sys.executable, "-c", PROBE.format(root=root, keep=keep)], capture_output=True,
                         text=True, check=True)
    return int(out.stdout.strip().splitlines()[-1])


def _glibc() -> bool:
    import platform
    return sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"


@pytest.mark.skipif(not _glibc(), reason="mallopt is glibc's")
def test_freed_blocks_are_reused_without_page_faults():
    # 20 steps of 4 x 1024 pages: by default about half of them are faulted in again every step
    assert _faults(keep=False) > 20 * 4096 // 4
    assert _faults(keep=True) < 1024


def test_keep_freed_memory_is_idempotent():
    first = keep_freed_memory()
    assert keep_freed_memory() is first
    assert first is _glibc() or not _glibc()
