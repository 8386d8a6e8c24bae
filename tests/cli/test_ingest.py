"""endowave-cl ingest (issue 58): a video or a folder of frames -> EndoNeRF layout, stereo depth by
semi-global matching, checked side folders, one-line errors and nothing half-written; `train VIDEO`."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from endowave_cl.cli import main
from endowave_cl.data.ingest import DISPARITY_COUNTS, IngestOptions, ingest
from endowave_cl.data.scene import load_scene
from endowave_cl.errors import DataError


def _texture(h, w, seed=0):
    rng = np.random.default_rng(seed)
    t = (rng.random((h, w)) * 255).astype(np.uint8)
    return cv2.GaussianBlur(t, (3, 3), 0)


def _write_video(path, frames, fps=10):
    """Encode frames (BGR uint8) with OpenCV: MPEG-4 in .mp4, else Motion JPEG in .avi."""
    h, w = frames[0].shape[:2]
    for fourcc, suffix in (("mp4v", ".mp4"), ("MJPG", ".avi")):
        p = path.with_suffix(suffix)
        vw = cv2.VideoWriter(str(p), cv2.VideoWriter_fourcc(*fourcc), fps, (w, h))
        if vw.isOpened():
            for f in frames:
                vw.write(f if f.ndim == 3 else cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))
            vw.release()
            if p.is_file() and p.stat().st_size > 0:
                return p
    pytest.skip("OpenCV here cannot encode a video")


def _moving_frames(n, h=48, w=64):
    base = cv2.cvtColor(_texture(h, w + n), cv2.COLOR_GRAY2BGR)
    return [np.ascontiguousarray(base[:, i:i + w]) for i in range(n)]


def _one_line(capsys):
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    return err


def test_video_range_stride_resize_and_fov(tmp_path, capsys):
    video = _write_video(tmp_path / "clip", _moving_frames(20))
    out = tmp_path / "scene"
    assert main(["ingest", str(video), str(out), "--start", "2", "--end", "18", "--stride", "2",
                 "--width", "32", "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "a guess" in text and "8 frames, 32x24" in text and "7 training / 1 test" in text, text
    scene = load_scene(out)
    assert len(scene.frames) == 8 and (scene.width, scene.height) == (32, 24)
    f_expect = 0.5 * 32 / np.tan(np.radians(60) / 2)
    assert scene.frames[0].camera.fx == pytest.approx(f_expect, rel=1e-5)
    info = json.loads((out / "scene.json").read_text())
    assert info["ingest"]["source_frames"] == [2, 4, 6, 8, 10, 12, 14, 16]
    # --focal is in source pixels: halved with the width; --max-frames caps the count
    r = ingest(video, tmp_path / "s2", IngestOptions(focal=100, width=32, max_frames=5), progress=False)
    assert r.frames == 5 and r.focal == pytest.approx(50) and not r.warnings


def test_folder_with_masks_checked_against_frames(tmp_path, capsys):
    src = tmp_path / "frames"
    masks = tmp_path / "masks"
    src.mkdir(), masks.mkdir()
    for i, f in enumerate(_moving_frames(10)):
        cv2.imwrite(str(src / f"f{i:03d}.jpg"), f)
        m = np.zeros(f.shape[:2], np.uint8)
        m[:10, :10] = 255
        cv2.imwrite(str(masks / f"m{i:03d}.png"), m)
    # one mask per source frame, stride 3: the same frames are taken
    r = ingest(src, tmp_path / "s", IngestOptions(stride=3, masks=str(masks), fov=70), progress=False)
    assert r.frames == 4 and r.has_masks
    scene = load_scene(tmp_path / "s")
    assert scene.frames[0].mask[:10, :10].max() == 0 and scene.frames[0].mask[20:, 20:].min() == 1
    # a mask of another size: one line naming the mask file, nothing written
    cv2.imwrite(str(masks / "m004.png"), np.zeros((40, 40), np.uint8))
    assert main(["ingest", str(src), str(tmp_path / "bad"), "--masks", str(masks), "--quiet"]) == 1
    err = _one_line(capsys)
    assert "m004.png" in err and "40x40" in err, err
    assert not (tmp_path / "bad").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]   # no temporary left
    # a count that fits neither the taken nor the source frames
    (masks / "m009.png").unlink()
    with pytest.raises(DataError, match="9 mask files"):
        ingest(src, tmp_path / "bad", IngestOptions(masks=str(masks)), progress=False)


@pytest.mark.parametrize("layout", ["side-by-side", "top-bottom"])
def test_stereo_depth_from_known_disparity(tmp_path, layout):
    """A rectified pair whose right view is the left one shifted by a known disparity (8 px above,
    12 px below): depth = f B / d comes back within 2 % (median) on at least 70 % of each region."""
    h, w, f, baseline = 64, 96, 80.0, 5.0
    tex = _texture(h, w + 16, seed=1)
    left = tex[:, :w].copy()
    right = np.empty_like(left)
    right[: h // 2] = tex[: h // 2, 8:8 + w]          # right[x] = left[x + d]
    right[h // 2:] = tex[h // 2:, 12:12 + w]
    pair = np.concatenate([left, right], axis=1 if layout == "side-by-side" else 0)
    video = _write_video(tmp_path / "stereo", [pair] * 3)
    if video.suffix == ".mp4":    # MPEG-4 at default quality blurs the texture: write lossless frames
        video = tmp_path / "frames"
        video.mkdir()
        for i in range(3):
            cv2.imwrite(str(video / f"{i}.png"), pair)
    r = ingest(video, tmp_path / "s", IngestOptions(stereo=layout, baseline=baseline, focal=f), progress=False)
    assert r.has_depth and (r.width, r.height) == (w, h)
    info = json.loads((tmp_path / "s" / "scene.json").read_text())
    assert info["depth_scale"] == pytest.approx(f * baseline / DISPARITY_COUNTS)
    raw = cv2.imread(str(tmp_path / "s" / "depth" / "000000.png"), cv2.IMREAD_UNCHANGED)
    depth = raw.astype(np.float64) * info["depth_scale"]
    for rows, d in ((slice(4, h // 2 - 4), 8), (slice(h // 2 + 4, h - 4), 12)):
        region = depth[rows, 16:w - 8]
        valid = region > 0
        assert valid.mean() > 0.7, (d, valid.mean())
        assert np.median(region[valid]) == pytest.approx(f * baseline / d, rel=0.02)
    scene = load_scene(tmp_path / "s")
    assert scene.has_depth and scene.near < scene.far


def test_odd_stereo_frame_broken_video_and_bad_options(tmp_path, capsys):
    odd = tmp_path / "odd"
    odd.mkdir()
    cv2.imwrite(str(odd / "0.png"), np.zeros((20, 33, 3), np.uint8))
    cv2.imwrite(str(odd / "1.png"), np.zeros((20, 33, 3), np.uint8))
    assert main(["ingest", str(odd), str(tmp_path / "o"), "--stereo", "side-by-side", "--baseline", "1"]) == 1
    err = _one_line(capsys)
    assert str(odd) in err and "even width" in err and "33x20" in err, err
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"\x00\x00\x00\x20ftypisom" + bytes(500))
    assert main(["ingest", str(broken), str(tmp_path / "b")]) == 1
    err = _one_line(capsys)
    assert "broken.mp4" in err, err
    assert not (tmp_path / "b").exists() and not (tmp_path / "o").exists()
    assert main(["ingest", str(odd), str(tmp_path / "o"), "--stereo", "side-by-side"]) == 1
    assert "--baseline" in _one_line(capsys)
    assert main(["ingest", str(odd), str(tmp_path / "o"), "--focal", "5", "--fov", "50"]) == 1
    assert "not both" in _one_line(capsys)


def test_train_accepts_a_video(tmp_path, capsys):
    video = _write_video(tmp_path / "clip", _moving_frames(10))
    run = tmp_path / "run"
    args = ["train", str(video), "--out", str(run), "--iterations", "3", "--quiet", "--no-flow",
            "--no-wavelet", "--set", "between_prob=0", "--set", "eval_every=0"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "ingesting it into" in out and "final test PSNR" in out, out
    assert (run / "scene" / "poses_bounds.npy").is_file()
    final = json.loads((run / "train_log.json").read_text())["final"]
    assert final["build_seconds"] >= 0 and final["train_seconds"] >= 0     # reported apart
    assert main(args + ["--iterations", "4"]) == 0          # resume: the same ingested scene
    assert "ingested from" in capsys.readouterr().out
    other = _write_video(tmp_path / "other", _moving_frames(10)[::-1])
    assert main(["train", str(other), "--out", str(run), "--quiet"]) == 1
    assert "not " + str(other) in _one_line(capsys)
