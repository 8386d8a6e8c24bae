"""Atomic writes: a file appears complete under its final name, or not at all.

Temporary files are named ``.<final name>.<pid>.<random>.tmp`` beside the final file, so a later
process can tell a temporary left by a killed writer (its pid no longer runs) from one being
written right now (``stale_temporaries``).  Finished files get the permissions an ordinary
``open()`` would give them (0666 minus the umask), not mkstemp's private 0600.
"""
from __future__ import annotations

import contextlib
import os
import re
import tempfile
from pathlib import Path

# .<name>.<pid>.<random>.tmp, as written by atomic_open (data/atomic.atomic_directory uses the
# same pattern for folders; a trailing extension is allowed for writers that need one, e.g. .tmp.mp4)
TEMP_RE = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)\.[^.]+\.tmp(\.\w+)?$")


def _umask() -> int:
    # os.umask can only be read by setting it; set it straight back
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def default_file_mode() -> int:
    """The mode ``open(path, "w")`` would give a new file under the current umask."""
    return 0o666 & ~_umask()


def temp_prefix(name: str) -> str:
    return f".{name}.{os.getpid()}."


def pid_alive(pid: int) -> bool:
    """Whether a process with this id exists (one of another user counts as alive)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def stale_temporaries(folder):
    """Temporary files or folders in ``folder`` left by writers whose process is gone."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    out = []
    for p in folder.iterdir():
        m = TEMP_RE.match(p.name)
        if m and int(m.group("pid")) != os.getpid() and not pid_alive(int(m.group("pid"))):
            out.append(p)
    return sorted(out)


@contextlib.contextmanager
def atomic_open(path):
    """Open a temporary file beside ``path`` for binary writing; on success it is flushed, synced
    and renamed onto ``path``; on any error it is removed and ``path`` is left as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=temp_prefix(path.name), suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fchmod(f.fileno(), default_file_mode())
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def write_bytes_atomic(path, data: bytes) -> None:
    """Write ``data`` to a temporary file beside ``path``, then rename it onto ``path``."""
    with atomic_open(path) as f:
        f.write(data)


def json_safe(obj):
    """``obj`` with every non-finite float replaced by None: JSON has no NaN or Infinity, and
    Python's ``json`` would write them as bare words that other readers reject."""
    import math
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    try:  # numpy scalars
        import numpy as np
        if isinstance(obj, np.floating):
            return json_safe(float(obj))
        if isinstance(obj, np.integer):
            return int(obj)
    except ImportError:  # pragma: no cover
        pass
    return obj


def write_json_atomic(path, obj, indent: int = 1) -> None:
    """Strict JSON (non-finite floats become null) written atomically."""
    import json
    write_bytes_atomic(path, json.dumps(json_safe(obj), indent=indent, allow_nan=False).encode())
