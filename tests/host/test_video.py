"""render's video and colour depth (issue 58): H.264 in MP4 from imageio-ffmpeg's FFmpeg, decoded back;
the OpenCV fallback; the turbo depth image; in Chromium (when present) the video plays."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from endowave_cl.video import depth_colour, depth_range, h264_available, video_codec, write_video

CHROMIUM = os.environ.get("ENDOWAVE_CHROMIUM", "/usr/bin/chromium")


def _frames(n=12, h=47, w=65):
    """Smooth moving gradients (odd sizes: yuv420p needs even ones, which the writer pads to)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    out = []
    for i in range(n):
        r = 0.5 + 0.5 * np.sin((x + 2 * i) / 9.0)
        g = 0.5 + 0.5 * np.cos((y - i) / 7.0)
        b = np.full_like(r, i / n)
        out.append((np.stack([r, g, b], -1) * 255 + 0.5).astype(np.uint8))
    return out


def _decode(path):
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(f[..., ::-1])
    cap.release()
    return frames


@pytest.mark.skipif(not h264_available(), reason="imageio-ffmpeg is not installed")
def test_h264_mp4_decodes_back(tmp_path):
    frames = _frames()
    path = tmp_path / "video.mp4"
    assert write_video(path, frames, fps=15) == "h264"
    assert video_codec(path) in ("h264", "avc1")
    back = _decode(path)
    assert len(back) == len(frames)
    assert back[0].shape == (48, 66, 3)                      # padded to even sides
    mse = np.mean([(b[:47, :65].astype(float) - f) ** 2 for b, f in zip(back, frames)])
    assert 10 * np.log10(255 ** 2 / mse) > 30                 # 34.5 dB here (CRF 18, 4:2:0 chroma)
    assert [p.name for p in tmp_path.iterdir()] == ["video.mp4"]   # no temporary left


def test_fallback_codec_and_nothing_half_written(tmp_path):
    path = tmp_path / "v.mp4"
    assert write_video(path, _frames(4, 48, 64), fps=10, codec="mp4v") == "mp4v"
    assert len(_decode(path)) == 4
    with pytest.raises(ValueError):
        write_video(tmp_path / "empty.mp4", [], fps=10)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.mp4"]


def test_depth_colour_red_near_blue_far_black_invalid():
    d = np.array([[1.0, 2.0, 3.0, 0.0]], np.float32)
    valid = d > 0
    lo, hi = depth_range([d], [valid], percentiles=(0, 100))
    assert (lo, hi) == (1.0, 3.0)
    rgb = depth_colour(d, valid, lo, hi)
    assert rgb.dtype == np.uint8 and rgb.shape == (1, 4, 3)
    near, far, none = rgb[0, 0].astype(int), rgb[0, 2].astype(int), rgb[0, 3]
    assert near[0] > near[2] and far[2] > far[0] and not none.any()


@pytest.mark.slow
@pytest.mark.skipif(not h264_available(), reason="imageio-ffmpeg is not installed")
def test_video_plays_in_chromium(tmp_path):
    """The browser test: a <video> of render's file loads its first frame in Chromium."""
    if not Path(CHROMIUM).is_file():
        pytest.skip(f"no Chromium at {CHROMIUM}")
    sync_api = pytest.importorskip("playwright.sync_api")
    write_video(tmp_path / "video.mp4", _frames(), fps=15)
    (tmp_path / "page.html").write_text(
        '<video id="v" src="video.mp4" muted></video><script>const v = document.getElementById("v");'
        'v.addEventListener("loadeddata", () => { document.title = "ok " + v.videoWidth; });'
        'v.addEventListener("error", () => { document.title = "error " + (v.error && v.error.code); });'
        '</script>')
    with sync_api.sync_playwright() as pw:
        profile = tempfile.mkdtemp(prefix="endowave-chromium-")
        ctx = pw.chromium.launch_persistent_context(
            profile, executable_path=CHROMIUM, args=["--headless", "--no-sandbox", "--disable-gpu",
                                                      "--allow-file-access-from-files", "--no-first-run"])
        try:
            page = ctx.new_page()
            page.goto((tmp_path / "page.html").as_uri())
            page.wait_for_function("document.title.length > 0", timeout=30000)
            assert page.title() == "ok 66", page.title()
        finally:
            ctx.close()
