"""Screenshot of `endowave-cl view` for the README (docs/viewer.png): the run at one frame's time,
with the ground-truth and error panes on, in headless Chromium (Debian's, driven by Playwright).

    python research/screenshot_viewer.py RUN [--frame 33] [--height 512] [--out docs/viewer.png]
"""
from __future__ import annotations

import argparse
import os
import shutil
import socket
import sys
import tempfile
import time
from pathlib import Path


CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("--frame", type=int, default=33)
    ap.add_argument("--height", default="512")
    ap.add_argument("--mode", default="colour")
    ap.add_argument("--no-panes", action="store_true")
    ap.add_argument("--browser-renderer", action="store_true", help="the client-side splat mode")
    ap.add_argument("--out", default="docs/viewer.png")
    ap.add_argument("--chromium", default=os.environ.get("ENDOWAVE_CHROMIUM", "/usr/bin/chromium"))
    a = ap.parse_args()
    from playwright.sync_api import sync_playwright

    from endowave_cl.run_io import load_run
    from endowave_cl.runtime import get_runtime
    from endowave_cl.viewer import ViewerModel
    from endowave_cl.viewer_app import ViewerApp
    r = load_run(a.run)
    model = ViewerModel(r, get_runtime())
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    title = f"{Path(a.run).name}: {Path(r.scene.path).name}, {len(r.gaussians)} Gaussians, step {r.step}"
    app = ViewerApp(model, "127.0.0.1", port, title).start()
    profile = tempfile.mkdtemp(prefix="shot-chromium-")
    try:
        with sync_playwright() as pw:
            ctx = pw.chromium.launch_persistent_context(profile, executable_path=a.chromium, args=CHROMIUM_ARGS,
                                                        headless=True, viewport={"width": 1400, "height": 760})
            page = ctx.new_page()
            page.goto(app.url)
            page.wait_for_function("() => /image \\d+ ·/.test(document.body.innerText)", timeout=300e3)
            # hide the software-WebGL notice that headless Chromium (no GPU) gets
            page.add_style_tag(content="[class*='Notification'] { display: none !important; }")
            s = next(iter(app.sessions.values()))
            s.resolution.value = a.height
            s.mode.value = a.mode
            if not a.no_panes:
                s.gt.value = True
                s.err.value = True
            if a.browser_renderer:
                s.renderer.value = "browser: 3D splats at t"
            s.time.value = float(model.times[a.frame])
            n = s.images_sent
            time.sleep(1.0)
            page.wait_for_function(f"() => {{ const m = document.body.innerText.match(/image (\\d+) ·/); "
                                   f"return m && +m[1] > {n}; }}", timeout=120e3)
            time.sleep(3.0)                                          # the browser draws the image
            Path(a.out).parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=a.out)
            print(f"wrote {a.out}: {page.inner_text('body').split('image ')[-1].strip()[:120]}")
            ctx.close()
    finally:
        app.stop()
        shutil.rmtree(profile, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
