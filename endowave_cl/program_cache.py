"""The kernel sources and the disk cache of built programs.

Kernels live in the top-level ``cl/`` folder of the source tree (installed as ``endowave_cl/cl``).
A built program is kept on disk under a key made of the kernel file, every header it includes
(however deep: an edited header is a new key), the build options and the device and driver
(:func:`cache_key`); an entry is a magic line, a JSON header line and the driver's binary
(:func:`_write_cache_entry`, :func:`_read_cache_entry`).  Building and loading: runtime.Runtime.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path
from typing import List, Sequence, Tuple

from . import env
from .device import DeviceCaps, _cl

ENV_KERNEL_DIR = "ENDOWAVE_CL_KERNELS"
ENV_CACHE_DIR = "ENDOWAVE_CL_CACHE"
ENV_NO_DISK_CACHE = "ENDOWAVE_CL_NO_DISK_CACHE"


def kernel_dir() -> Path:
    """Folder holding the *.cl / *.h kernel sources."""
    kdir = env.get(ENV_KERNEL_DIR)
    if kdir:
        return Path(kdir)
    here = Path(__file__).resolve().parent
    for cand in (here / "cl", here.parent / "cl"):  # installed, then source tree
        if cand.is_dir() and any(cand.glob("*.cl")):
            return cand
    raise FileNotFoundError(
        f"OpenCL kernel sources not found next to {here} (looked in {here / 'cl'} and "
        f"{here.parent / 'cl'}); reinstall endowave-cl or set {ENV_KERNEL_DIR}")



def _default_cache_dir() -> Path:
    cache = env.get(ENV_CACHE_DIR)
    if cache:
        return Path(cache)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "endowave-cl" / "programs"



_INCLUDE_RE = re.compile(r'^\s*#\s*include\s+"([^"]+)"', re.MULTILINE)


def _source_with_includes_hash(path: Path, h, seen=None) -> None:
    """Feed a kernel file and every quoted #include it pulls in (recursively) into h."""
    seen = set() if seen is None else seen
    if path in seen:
        return
    seen.add(path)
    text = path.read_bytes()
    h.update(path.name.encode() + b"\0" + text + b"\0")
    for inc in _INCLUDE_RE.findall(text.decode("utf-8", "replace")):
        p = path.parent / inc
        if p.is_file():
            _source_with_includes_hash(p, h, seen)


_CACHE_MAGIC = b"endowave-cl program\n"


def _kernel_names(prg) -> List[str]:
    cl = _cl()
    names = prg.get_info(cl.program_info.KERNEL_NAMES) or ""
    return [n for n in names.split(";") if n]


def _write_cache_entry(cache_file: Path, key: str, binary: bytes, kernels: Sequence[str]) -> None:
    """A disk-cache entry: magic line, a JSON header line (cache key, size and sha256 of the
    binary, kernel names), the driver's binary.  Written to a temporary file and renamed."""
    header = json.dumps({"key": key, "size": len(binary), "sha256": hashlib.sha256(binary).hexdigest(),
                         "kernels": list(kernels)}).encode()
    cache_file.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache_file.with_suffix(f".tmp{os.getpid()}")
    tmp.write_bytes(_CACHE_MAGIC + header + b"\n" + binary)
    os.replace(tmp, cache_file)


def _read_cache_entry(cache_file: Path, key: str) -> Tuple[bytes, List[str]]:
    """(binary, kernel names) of an entry written by _write_cache_entry for ``key``; ValueError
    saying what is wrong otherwise (foreign, truncated or altered file)."""
    data = cache_file.read_bytes()
    if not data.startswith(_CACHE_MAGIC):
        raise ValueError("no endowave-cl header")
    nl = data.find(b"\n", len(_CACHE_MAGIC))
    if nl < 0:
        raise ValueError("truncated header")
    header = json.loads(data[len(_CACHE_MAGIC):nl])
    binary = data[nl + 1:]
    if header.get("key") != key:
        raise ValueError("written for another build")
    if header.get("size") != len(binary) or header.get("sha256") != hashlib.sha256(binary).hexdigest():
        raise ValueError("binary does not match its checksum")
    return binary, list(header.get("kernels") or [])



def cache_key(path: Path, options: Sequence[str], device, caps: DeviceCaps) -> str:
    """The disk-cache key of kernel file ``path`` built with ``options`` on ``device``: the file
    and every header it includes, the options, the options every kernel gets (caps) and the
    device, platform and driver versions."""
    h = hashlib.sha256()
    _source_with_includes_hash(path, h)
    d = device
    h.update("\0".join([*options, caps.cl_std, *caps.build_options(), d.name, d.platform.name, d.version,
                         d.driver_version]).encode())
    return h.hexdigest()[:32]
