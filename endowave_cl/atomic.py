"""Atomic writes: a file or a folder appears complete under its final name, or not at all.

The one home of atomic writing: bytes (``atomic_open``, ``write_bytes_atomic``), JSON
(``write_json_atomic``), PNG (``save_png``, ``write_png_atomic``) and whole folders
(``atomic_directory``).

Temporary files are named ``.<final name>.<pid>.<random>.tmp`` beside the final file, so a later
process can tell a temporary left by a killed writer (its pid no longer runs) from one being
written right now (``stale_temporaries``).  Finished files get the permissions an ordinary
``open()`` would give them (0666 minus the umask), not mkstemp's private 0600.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import re
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np

from .errors import DataError

# .<name>.<pid>.<random>.tmp, as written by atomic_open (atomic_directory uses the same pattern
# for folders; a trailing extension is allowed for writers that need one, e.g. .tmp.mp4)
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


def named_oserror(e: OSError, path) -> OSError:
    """``e`` with the file or folder it concerns named, for the one-line error.  A write error from
    ``f.write`` carries no file name, and numpy's short write ("61440 requested and 60384 written",
    no errno) does not say why: a full disk."""
    if e.filename is not None:
        return e
    text = e.strerror or str(e)
    short = re.fullmatch(r"(\d+) requested and (\d+) written", text) if e.errno is None else None
    if short:
        text = f"only {short[2]} of {short[1]} bytes were written: is the disk full?"
    named = OSError(e.errno, text, str(path))
    named.__cause__ = e
    return named


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
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(e, OSError):
            raise named_oserror(e, path) from e
        raise


def write_bytes_atomic(path, data: bytes) -> None:
    """Write ``data`` to a temporary file beside ``path``, then rename it onto ``path``."""
    with atomic_open(path) as f:
        f.write(data)


def json_safe(obj):
    """``obj`` with every non-finite float replaced by None: JSON has no NaN or Infinity, and
    Python's ``json`` would write them as bare words that other readers reject."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.floating):   # numpy scalars
        return json_safe(float(obj))
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def write_json_atomic(path, obj, indent: int = 1) -> None:
    """Strict JSON (non-finite floats become null) written atomically."""
    write_bytes_atomic(path, json.dumps(json_safe(obj), indent=indent, allow_nan=False).encode())


def save_png(path, image, atomic: bool = True) -> None:
    """Encode ``image`` (uint8 or uint16, [H, W] or [H, W, 3] in BGR order) as PNG.

    ``atomic=False`` writes directly: for files inside a temporary folder that is renamed as a whole.
    """
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    if atomic:
        write_bytes_atomic(path, buf.tobytes())
    else:
        Path(path).write_bytes(buf.tobytes())


@contextlib.contextmanager
def atomic_directory(final, force: bool = False):
    """Yield a temporary folder beside ``final``; on success it replaces ``final``.

    ``final`` must be absent or empty unless ``force`` is true (then the old content is
    removed only after the new folder is complete).  On any error the temporary folder is
    deleted and ``final`` is left as it was.
    """
    final = Path(final)
    if final.exists():
        if not final.is_dir():
            raise DataError(f"{final}: exists and is not a folder")
        if any(final.iterdir()) and not force:
            raise DataError(f"{final}: folder is not empty (use --force to replace it)")
    final.parent.mkdir(parents=True, exist_ok=True)
    for stale in stale_temporaries(final.parent):    # of a writer of this folder that was killed
        m = TEMP_RE.match(stale.name)
        if m and m.group("name") == final.name and stale.is_dir() and not stale.is_symlink():
            shutil.rmtree(stale, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=temp_prefix(final.name), suffix=".tmp", dir=final.parent))
    try:
        os.chmod(tmp, 0o777 & ~_umask())   # mkdtemp's 0700 would make the finished folder private
        yield tmp
    except BaseException as e:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(e, OSError):
            raise named_oserror(e, final) from e
        raise
    old = None
    if final.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".old", dir=final.parent))
        os.rmdir(old)
        os.replace(final, old)
    os.replace(tmp, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def write_png_atomic(path, image) -> None:
    """image: [H, W, 3] float RGB in [0, 1], or [H, W] uint8/uint16; written atomically."""
    if image.dtype in (np.uint8, np.uint16):
        arr = image
    else:
        arr = (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)
    save_png(path, arr[..., ::-1] if arr.ndim == 3 else arr)  # RGB -> BGR for OpenCV
