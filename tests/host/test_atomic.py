"""atomic.py: a failed write leaves the final file or folder as it was, no temporary behind, and an
error that names the file (a write error from f.write or numpy's short write names none)."""
from __future__ import annotations

import errno

import pytest

from endowave_cl.atomic import atomic_directory, atomic_open, named_oserror


def test_short_write_is_named_and_explained(tmp_path):
    final = tmp_path / "model.npz"
    final.write_bytes(b"old")
    with pytest.raises(OSError) as info:
        with atomic_open(final) as f:
            f.write(b"new")
            raise OSError("61440 requested and 60384 written")    # what numpy raises on a full disk
    e = info.value
    assert e.filename == str(final) and e.errno is None
    assert e.strerror == "only 60384 of 61440 bytes were written: is the disk full?"
    assert final.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["model.npz"]


def test_write_error_without_a_name_gets_the_folder(tmp_path):
    final = tmp_path / "scene"
    with pytest.raises(OSError) as info:
        with atomic_directory(final) as tmp:
            (tmp / "a.npy").write_bytes(b"x")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(final)
    assert info.value.strerror == "No space left on device"
    assert list(tmp_path.iterdir()) == []


def test_named_errors_and_others_pass_unchanged(tmp_path):
    e = FileNotFoundError(errno.ENOENT, "No such file or directory", "/x/y")
    assert named_oserror(e, tmp_path) is e
    with pytest.raises(ValueError):
        with atomic_open(tmp_path / "f") as f:
            raise ValueError("not an OSError")
    assert list(tmp_path.iterdir()) == []
