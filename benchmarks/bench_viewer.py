"""Measure what `endowave-cl view` delivers to a real browser (headless Chromium via Playwright):

- images per second while playing, at each render height (width from the page's 1.25 aspect, so
  256 -> 320x256 and 512 -> 640x512), counted in the page (status-line updates observed there) and
  on the server;
- slider-to-image latency: from the key press that moves the time slider (timed in the page) to
  the status line of the image rendered for it arriving in the page (sent right after the image);
  with the server's own split (render + encode vs. the whole wait);
- the browser mode's refresh: Gaussians at t computed and sent.

    python benchmarks/bench_viewer.py RUN [--heights 256 512] [--seconds 15] [--latency-moves 15]

Prints one line per figure and `uptime` (the machine's load matters on a CPU device).
"""
from __future__ import annotations

import argparse
import os
import platform
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
VIEWPORT = {"width": 1000, "height": 800}     # of the 3D canvas (the window is wider by the panel)

# Installed in the page: every status-line change is time-stamped with the image number it shows,
# and every key press on the page too (capture phase, before the slider handles it).
OBSERVER_JS = """() => {
  window.__imgs = []; window.__keys = [];
  document.addEventListener('keydown', () => window.__keys.push(performance.now()), true);
  const seen = {n: -1};
  new MutationObserver(() => {
    const m = document.body.innerText.match(/image (\\d+) · t = ([0-9.]+)/);
    if (m && +m[1] !== seen.n) { seen.n = +m[1]; window.__imgs.push([performance.now(), +m[1], m[2]]); }
  }).observe(document.body, {subtree: true, childList: true, characterData: true});
}"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("--heights", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--seconds", type=float, default=15.0, help="playing time per resolution")
    ap.add_argument("--latency-moves", type=int, default=15)
    ap.add_argument("--device")
    ap.add_argument("--chromium", default=os.environ.get("ENDOWAVE_CHROMIUM", "/usr/bin/chromium"))
    a = ap.parse_args()

    from playwright.sync_api import sync_playwright

    from endowave_cl.run_io import load_run
    from endowave_cl.runtime import get_runtime
    from endowave_cl.viewer import ViewerModel
    from endowave_cl.viewer_app import ViewerApp
    r = load_run(a.run)
    rt = get_runtime(a.device)
    model = ViewerModel(r, rt)
    app = ViewerApp(model, "127.0.0.1", free_port(), "bench").start()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs; "
          f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"run {a.run}: {len(r.gaussians)} Gaussians, step {r.step}, on {rt.name}")
    profile = tempfile.mkdtemp(prefix="bench-chromium-")
    try:
        with sync_playwright() as pw:
            ctx = pw.chromium.launch_persistent_context(profile, executable_path=a.chromium, args=CHROMIUM_ARGS,
                                                        headless=True, viewport=VIEWPORT)
            page = ctx.new_page()
            page.goto(app.url)
            page.wait_for_function("() => /image \\d+ ·/.test(document.body.innerText)", timeout=300e3)
            # size the window so that the 3D canvas beside the panel is 1000 x 800 (aspect 1.25:
            # height 256 renders 320x256, 512 renders 640x512)
            box = max((c.bounding_box() for c in page.locator("canvas").all()),
                      key=lambda b: b["width"] * b["height"])
            page.set_viewport_size({"width": VIEWPORT["width"] + int(round(VIEWPORT["width"] - box["width"])),
                                    "height": VIEWPORT["height"]})
            time.sleep(2.0)
            page.evaluate(OBSERVER_JS)
            s = next(iter(app.sessions.values()))
            for h in a.heights:
                s.resolution.value = str(h)
                time.sleep(2.0)                                  # let the first image at this size settle
                w, hh = s.last.image.shape[1], s.last.image.shape[0]
                # -- the same view without the browser: render + colour + JPEG encode ----------------
                from endowave_cl.viewer import ViewState
                import cv2
                pose = (s.client.camera.wxyz, s.client.camera.position, s.client.camera.fov)
                ms = []
                for i in range(10):
                    t0 = time.perf_counter()
                    res = model.view(pose, ViewState(t=0.05 * i, height=h), w / hh, 1e-4)
                    cv2.imencode(".jpg", res.image[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])   # as viser does
                    ms.append((time.perf_counter() - t0) * 1e3)
                print(f"{w}x{hh}: in-process render + JPEG, no browser: median {statistics.median(ms):.0f} ms "
                      f"({1e3 / statistics.median(ms):.1f} images/s)")
                # -- playing: images per second ---------------------------------------------------
                n_srv0, t0 = s.images_sent, time.perf_counter()
                page.evaluate("() => { window.__imgs = []; }")
                s.toggle_play()
                time.sleep(a.seconds)
                s.toggle_play()
                n_srv, dt = s.images_sent - n_srv0, time.perf_counter() - t0
                imgs = page.evaluate("() => window.__imgs")
                time.sleep(1.0)
                page_fps = (len(imgs) - 1) / ((imgs[-1][0] - imgs[0][0]) / 1e3) if len(imgs) > 2 else float("nan")
                print(f"{w}x{hh}: playing {a.seconds:.0f} s: {page_fps:.2f} images/s arriving in the page, "
                      f"{n_srv / dt:.2f} images/s sent by the server")
                # -- slider to image ---------------------------------------------------------------
                slider = page.get_by_role("slider").first
                slider.focus()
                lat, srv = [], []
                for i in range(a.latency_moves):
                    # idle first, so that no image for an earlier state is in flight
                    time.sleep(max(0.6, 3e-3 * s.last.render_ms))
                    page.evaluate("() => { window.__imgs = []; window.__keys = []; }")
                    t_old = float(s.time.value)
                    page.keyboard.press("ArrowRight" if i % 2 == 0 else "ArrowLeft")
                    deadline = time.time() + 30
                    while float(s.time.value) == t_old and time.time() < deadline:
                        time.sleep(0.005)
                    t_new = f"{float(s.time.value):.3f}"
                    page.wait_for_function(f"() => window.__imgs.some(e => e[2] === '{t_new}')", timeout=60e3)
                    k, im = page.evaluate("() => [window.__keys, window.__imgs]")
                    first = min(e[0] for e in im if e[2] == t_new)
                    lat.append(first - k[0])
                    srv.append(s.latencies_ms[-1])
                med = statistics.median(lat)
                print(f"{w}x{hh}: slider -> image in the page: median {med:.0f} ms, min {min(lat):.0f}, "
                      f"max {max(lat):.0f} over {len(lat)} moves; server change -> image sent: median "
                      f"{statistics.median(srv):.0f} ms; render + compose of the last image {s.last.render_ms:.0f} ms")
            # -- browser mode -------------------------------------------------------------------------
            s.renderer.value = s.renderer.options[1] if hasattr(s.renderer, "options") else "browser: 3D splats at t"
            time.sleep(3.0)
            ms = []
            for i in range(5):
                t0 = time.perf_counter()
                model.splats_at(0.1 * (i + 1), s.client.camera.position)
                ms.append((time.perf_counter() - t0) * 1e3)
            print(f"browser mode: Gaussians at t computed in median {statistics.median(ms):.0f} ms "
                  f"(page status: {page.inner_text('body').split('image ')[-1].strip()[:80]})")
            ctx.close()
    finally:
        app.stop()
        shutil.rmtree(profile, ignore_errors=True)
    print("uptime:", subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
    return 0


if __name__ == "__main__":
    sys.exit(main())
