"""Each kind of bad input gives a DataError whose message names the offending file."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from endowave_cl.data import load_scene
from endowave_cl.atomic import save_png
from endowave_cl.data.synth import make_synthetic_scene
from endowave_cl.errors import DataError


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    return make_synthetic_scene(tmp_path_factory.mktemp("syn") / "scene", width=32, height=24, frames=4, seed=1)


@pytest.fixture
def scene(good, tmp_path):
    d = tmp_path / "s"
    shutil.copytree(good, d)
    load_scene(d)          # the unbroken copy loads
    return d


def _fails(scene_dir, culprit, words):
    with pytest.raises(DataError) as e:
        load_scene(scene_dir)
    msg = str(e.value)
    assert str(culprit) in msg, msg
    assert words in msg, msg


def test_missing_poses(scene):
    (scene / "poses_bounds.npy").unlink()
    _fails(scene, scene / "poses_bounds.npy", "missing")


def test_malformed_poses(scene):
    np.save(scene / "poses_bounds.npy", np.zeros((4, 15)))
    _fails(scene, scene / "poses_bounds.npy", "shape (N, 17)")
    (scene / "poses_bounds.npy").write_bytes(b"not numpy")
    _fails(scene, scene / "poses_bounds.npy", "not a readable")


def test_pose_count_mismatch(scene):
    np.save(scene / "poses_bounds.npy", np.load(scene / "poses_bounds.npy")[:3])
    _fails(scene, scene / "poses_bounds.npy", "3 poses but 4 images")


def test_mask_and_depth_count_mismatch(scene):
    (scene / "masks" / "000002.png").unlink()
    _fails(scene, scene / "masks", "3 mask files but 4 images")
    shutil.copy(scene / "images" / "000002.png", scene / "masks" / "000002.png")
    (scene / "depth" / "000003.png").unlink()
    _fails(scene, scene / "depth", "3 depth files but 4 images")


def test_truncated_image(scene):
    f = scene / "images" / "000001.png"
    data = f.read_bytes()
    f.write_bytes(data[: len(data) // 2])
    _fails(scene, f, "unreadable or truncated")


def test_unreadable_image(scene):
    f = scene / "images" / "000002.png"
    f.write_bytes(b"\x89PNG but not really")
    _fails(scene, f, "unreadable or truncated")


def test_image_sizes_disagree(scene):
    f = scene / "images" / "000003.png"
    save_png(f, np.zeros((24, 30, 3), np.uint8))
    _fails(scene, f, "size 30x24 disagrees with the 32x24")


def test_depth_and_mask_size_disagree(scene):
    f = scene / "depth" / "000001.png"
    save_png(f, np.ones((20, 32), np.uint16))
    _fails(scene, f, "size 32x20 disagrees")
    f.unlink()
    shutil.copy(scene / "depth" / "000000.png", f)
    f = scene / "masks" / "000000.png"
    save_png(f, np.zeros((24, 31), np.uint8))
    _fails(scene, f, "size 31x24 disagrees")


def test_depth_without_valid_pixel(scene):
    f = scene / "depth" / "000002.png"
    save_png(f, np.zeros((24, 32), np.uint16))
    _fails(scene, f, "no valid")


def test_hwf_that_matches_nothing(scene):
    arr = np.load(scene / "poses_bounds.npy")
    arr[:, 4], arr[:, 9] = 100.0, 200.0      # neither 24x32 nor a point inside it
    np.save(scene / "poses_bounds.npy", arr)
    (scene / "scene.json").write_text("{}")
    _fails(scene, scene / "poses_bounds.npy", "matches neither the image size")


def test_bad_bounds_and_bad_json(scene):
    arr = np.load(scene / "poses_bounds.npy")
    arr[:, 16] = arr[:, 15]
    np.save(scene / "poses_bounds.npy", arr)
    _fails(scene, scene / "poses_bounds.npy", "near")
    (scene / "scene.json").write_text("{broken")
    _fails(scene, scene / "scene.json", "not valid JSON")


def test_missing_images_folder(tmp_path):
    np.save(tmp_path / "poses_bounds.npy", np.zeros((1, 17)))
    _fails(tmp_path, tmp_path / "images", "missing")
    with pytest.raises(DataError, match="scene folder not found"):
        load_scene(tmp_path / "nope")


# ------------------------------------------------------------------ issue #14: poses and sizes
def _set_rotation(scene, row, R):
    arr = np.load(scene / "poses_bounds.npy")
    pose = arr[row, :15].reshape(3, 5)
    pose[:, :3] = R
    arr[row, :15] = pose.reshape(-1)
    np.save(scene / "poses_bounds.npy", arr)


@pytest.mark.parametrize("R,words", [
    (np.zeros((3, 3)), "not orthonormal"),
    (np.array([[1.0, 0, 0], [0, 1, 0], [1, 0, 0]]), "not orthonormal"),      # singular
    (np.eye(3) * 1e-9, "not orthonormal"),
    (np.eye(3) * 1.01, "not orthonormal"),
    (np.diag([1.0, 1.0, -1.0]), "determinant -1"),                          # a mirror
])
def test_bad_pose_rotation_names_the_row(scene, R, words):
    _set_rotation(scene, 2, R)
    _fails(scene, f"{scene / 'poses_bounds.npy'} (row 2)", words)


def test_rotation_within_tolerance_is_accepted(scene):
    c, s = np.cos(0.3), np.sin(0.3)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).astype(np.float32).astype(np.float64)
    _set_rotation(scene, 1, R)
    load_scene(scene)


def test_poses_stored_as_strings(scene):
    arr = np.load(scene / "poses_bounds.npy").astype(str)
    np.save(scene / "poses_bounds.npy", arr)
    load_scene(scene)                     # numbers written as text are still numbers
    arr[3, 5] = "abc"
    np.save(scene / "poses_bounds.npy", arr)
    _fails(scene, scene / "poses_bounds.npy", "row 3 holds 'abc', not a number")
    np.save(scene / "poses_bounds.npy", np.zeros((4, 17), complex))
    _fails(scene, scene / "poses_bounds.npy", "poses must be stored as floats")


def test_nan_pose_names_the_row(scene):
    arr = np.load(scene / "poses_bounds.npy")
    arr[2, 7] = np.nan
    np.save(scene / "poses_bounds.npy", arr)
    _fails(scene, scene / "poses_bounds.npy", "row 2 contains NaN")


def test_odd_first_image_is_blamed_not_depth(scene):
    f = scene / "images" / "000000.png"
    save_png(f, np.zeros((24, 30, 3), np.uint8))
    _fails(scene, f, "size 30x24 disagrees with the 32x24 of the other images")
