"""Atomic writes: a file or a folder appears complete under its final name, or not at all."""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np

from ..atomic import _umask, temp_prefix, write_bytes_atomic  # noqa: F401  (write_bytes_atomic is re-exported for the data modules)


def save_npy_atomic(path, array: np.ndarray) -> None:
    """``np.save`` through a temporary file and a rename."""
    import io
    buf = io.BytesIO()
    np.save(buf, np.asarray(array), allow_pickle=False)
    write_bytes_atomic(path, buf.getvalue())


def save_png(path, image: np.ndarray, atomic: bool = True) -> None:
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
    from ..errors import DataError
    final = Path(final)
    if final.exists():
        if not final.is_dir():
            raise DataError(f"{final}: exists and is not a folder")
        if any(final.iterdir()) and not force:
            raise DataError(f"{final}: folder is not empty (use --force to replace it)")
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=temp_prefix(final.name), suffix=".tmp", dir=final.parent))
    try:
        os.chmod(tmp, 0o777 & ~_umask())   # mkdtemp's 0700 would make the finished folder private
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    if final.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".old", dir=final.parent))
        os.rmdir(old)
        os.replace(final, old)
    os.replace(tmp, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
