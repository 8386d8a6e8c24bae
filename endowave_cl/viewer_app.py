"""The viser side of ``endowave-cl view``: one web page per browser, each with its own time, camera
and settings, rendered by endowave_cl/viewer.py and streamed as the page's background image.

Each connected browser gets a :class:`Session`: a GUI panel (time slider with the frame times
marked, play / pause, frame stepping, renderer, what to show, resolution, the ground-truth / error /
tool-mask panes, a "frame camera" button back to the training camera of the frame at the slider,
a status line) and a render thread that wakes when the camera or a setting changes
and renders the newest state only (older requests are dropped, so a slow device never queues a
backlog).  The browser renderer mode sends the 3D Gaussians at the slider time to viser's own splat
renderer instead and re-sends them when the time changes.

The orbit is gentle (viewer.gentle_pose): the server renderer renders from the browser camera's
turn away from the frame camera scaled by ORBIT_SENSITIVITY (0.25) and clamped at ORBIT_MAX_DEG
(30 degrees), and pulls the browser camera back once it has turned past the point where the clamp
bites (120 degrees), so turning back answers at once.  The browser renderer draws the browser
camera itself: there the turn is clamped at ORBIT_MAX_DEG by the same pull-back, not scaled.
"""
from __future__ import annotations

import collections
import contextlib
import errno
import io
import math
import socket
import sys
import threading
import time
from typing import Dict, Optional

import numpy as np

from .errors import EndowaveError
from .viewer import ORBIT_MAX_DEG, ORBIT_SENSITIVITY, MODES, ViewerModel, ViewResult, ViewState, gentle_pose

TIME_STEP = 0.001                 # slider resolution in normalised time
PLAY_FRAMES_PER_S = 10.0          # play speed: sequence frames per second of wall time
PLAY_TICK_S = 1.0 / 30            # how often play moves the slider
RESOLUTIONS = ("128", "256", "512", "768")   # render heights; the width follows the browser's aspect
DEFAULT_RESOLUTION = "256"
JPEG_QUALITY = 90
RENDERERS = ("server: OpenCL (exact)", "browser: 3D splats at t")
MAX_MARK_LABELS = 9               # frame-time marks beyond this many are drawn without numbers


def port_problem(host: str, port: int) -> Optional[str]:
    """Why ``port`` cannot be listened on at ``host`` now (bound with SO_REUSEADDR, as the server
    binds), or None when it can."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except OSError as e:
        return f"cannot resolve --host {host}: {e.strerror or e}"
    fam, _, _, _, addr = infos[0]
    with socket.socket(fam, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(addr)
        except OSError as e:
            if e.errno == errno.EADDRINUSE:
                return f"port {port} is already in use on {host}; pick another with --port"
            return f"cannot listen on {host}:{port}: {e.strerror or e}"
    return None


def port_free(host: str, port: int) -> bool:
    return port_problem(host, port) is None


def _marks(times: np.ndarray):
    """Slider marks at the frame times; numbers on at most MAX_MARK_LABELS of them."""
    n = len(times)
    every = max(1, math.ceil((n - 1) / (MAX_MARK_LABELS - 1))) if n > 1 else 1
    return tuple((float(t), str(k)) if (k % every == 0 or k == n - 1) else float(t)
                 for k, t in enumerate(times))


class Session:
    """One browser tab: its GUI, its state and its render thread."""

    def __init__(self, app: "ViewerApp", client):
        self.app, self.client, self.model = app, client, app.model
        m = self.model
        self.dirty = threading.Event()
        self.closed = False
        self.have_camera = False
        self.playing = False
        self.images_sent = 0
        self.last: Optional[ViewResult] = None
        self.sent_times = collections.deque(maxlen=30)      # send times of recent images, for img/s
        self.pending_since: Optional[float] = None          # when the oldest unrendered change arrived
        self.latencies_ms = collections.deque(maxlen=200)   # change -> image queued, server side
        self._splat_t: Optional[float] = None
        self._since: Optional[float] = None
        self._error_said = False
        self.home_frame = 0                                  # the frame camera the orbit turns around
        self.home_wxyz = m.home_pose(0)["wxyz"]
        self.orbit_deg = 0.0
        gui = client.gui
        tol = min(TIME_STEP / 2, m.dt_frame / 4)
        self.tol = tol
        gui.add_markdown(f"**{app.title}**")
        self.time = gui.add_slider("time", 0.0, 1.0, TIME_STEP, 0.0, marks=_marks(m.times),
                                   hint="normalised time; the marks are the frame times")
        self.play = gui.add_button("play", hint="play / pause the sequence")
        self.prev = gui.add_button("previous frame")
        self.next = gui.add_button("next frame")
        self.home_button = gui.add_button("frame camera", hint="back to the training camera of the frame "
                                                               "at the slider (the orbit turns around it)")
        self.renderer = gui.add_dropdown("renderer", RENDERERS, initial_value=RENDERERS[0],
                                         hint="server: our OpenCL rasterizer, streamed; browser: the Gaussians "
                                              "at t in viser's WebGL splat renderer (view-dependent colour "
                                              "frozen at the camera position of the last refresh)")
        self.mode = gui.add_dropdown("show", MODES, initial_value="colour")
        self.resolution = gui.add_dropdown("render height (px)", RESOLUTIONS, initial_value=DEFAULT_RESOLUTION,
                                           hint="lower = faster on a CPU; the width follows the window")
        self.gt = gui.add_checkbox("ground truth beside", False, hint="at frame times: the training image")
        self.err = gui.add_checkbox("per-pixel error", False,
                                    hint="at frame times: |render - truth| from that frame's camera")
        has_masks = m.scene.has_masks
        self.mask = gui.add_checkbox("tool mask", False, disabled=not has_masks,
                                     hint="at frame times: tool pixels in red" if has_masks
                                     else "this scene has no masks/")
        self.status = gui.add_markdown("waiting for the browser's camera")

        for h in (self.time, self.mode, self.resolution, self.gt, self.err, self.mask, self.renderer):
            h.on_update(self._on_setting)
        self.play.on_click(lambda _: self.toggle_play())
        self.prev.on_click(lambda _: self.step_frame(-1))
        self.next.on_click(lambda _: self.step_frame(+1))
        self.home_button.on_click(lambda _: self.back_to_frame_camera())
        client.camera.on_update(self._on_camera)
        try:     # the browser's first camera message may have come before the callback was attached
            client.camera.update_timestamp      # asserts until a camera message has arrived
            self._on_camera(client.camera)
        except AssertionError:
            pass
        self.thread = threading.Thread(target=self._loop, name=f"view-render-{client.client_id}", daemon=True)
        self.thread.start()

    # -- events (viser threads) ------------------------------------------------------------------

    def _mark_dirty(self):
        if self.pending_since is None:
            self.pending_since = time.perf_counter()
        self.dirty.set()

    def _on_setting(self, _event):
        self._mark_dirty()

    def _on_camera(self, _camera):
        self.have_camera = True
        if self.renderer.value == RENDERERS[0]:     # the browser mode renders camera moves itself
            self._mark_dirty()
        else:                                       # ... but its turn is clamped, unscaled
            self.gentle(sensitivity=1.0)

    def gentle(self, sensitivity: float = ORBIT_SENSITIVITY):
        """The gentle orbit for the browser camera now (viewer.gentle_pose); pulls the browser
        camera back when it has turned past the point where the clamp bites."""
        c = self.client.camera
        g = gentle_pose(np.asarray(c.wxyz), np.asarray(c.position), np.asarray(c.look_at), self.home_wxyz,
                        sensitivity=sensitivity)
        if g.limit_position is not None:
            look_at = np.array(c.look_at)
            self._set_camera(position=g.limit_position, look_at=look_at)
        self.orbit_deg = g.deg
        return g

    def _set_camera(self, position, look_at, up=None, fov=None):
        c = self.client.camera
        atomic = getattr(self.client, "atomic", None)
        with (atomic() if atomic is not None else contextlib.nullcontext()):
            if up is not None:
                c.up_direction = tuple(float(v) for v in up)
            c.position = tuple(float(v) for v in position)      # moves look_at along ...
            c.look_at = tuple(float(v) for v in look_at)        # ... so set it after
            if fov is not None:
                c.fov = float(fov)

    def back_to_frame_camera(self):
        """Put the browser camera on the training camera of the frame nearest the slider time,
        looking at the tissue; the gentle orbit turns around it from now on."""
        k = self.model.nearest_frame(float(self.time.value))
        home = self.model.home_pose(k)
        self.home_frame, self.home_wxyz = k, home["wxyz"]
        if self.have_camera:
            self._set_camera(home["position"], home["look_at"], home["up"], home["fov"])
        self._mark_dirty()

    def toggle_play(self):
        self.playing = not self.playing
        self.play.label = "pause" if self.playing else "play"
        if self.playing:
            threading.Thread(target=self._play, name="view-play", daemon=True).start()

    def step_frame(self, d: int):
        """Move the slider to the previous / next frame time."""
        times = self.model.times
        t = float(self.time.value)
        k = int(np.searchsorted(times, t - self.tol, side="left")) if d < 0 else \
            int(np.searchsorted(times, t + self.tol, side="right"))
        k = k - 1 if d < 0 else k
        self.time.value = float(times[int(np.clip(k, 0, len(times) - 1))])

    def _play(self):
        speed = PLAY_FRAMES_PER_S * self.model.dt_frame     # normalised time per second
        last = time.perf_counter()
        while self.playing and not self.closed:
            time.sleep(PLAY_TICK_S)
            now = time.perf_counter()
            t = float(self.time.value) + speed * (now - last)
            last = now
            self.time.value = round(t % 1.0 if t > 1.0 else t, 6)

    # -- rendering (this session's thread) -------------------------------------------------------

    def _snapshot(self) -> ViewState:
        return ViewState(t=float(self.time.value), mode=str(self.mode.value), height=int(self.resolution.value),
                         show_gt=bool(self.gt.value), show_error=bool(self.err.value),
                         show_mask=bool(self.mask.value))

    def _loop(self):
        while not self.closed:
            if not self.dirty.wait(timeout=0.5):
                continue
            if self.closed or not self.have_camera:
                continue
            self.dirty.clear()
            since, self.pending_since = self.pending_since, None
            try:
                self.render_once(since)
                self._error_said = False
            except Exception as e:  # noqa: BLE001  shown on the page and once on the console, never a traceback
                msg = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
                self.status.content = f"render failed: {msg}"
                if not self._error_said:
                    print(f"endowave-cl view: render failed: {msg}", file=sys.stderr)
                    self._error_said = True

    def render_once(self, since: Optional[float] = None):
        """Render the current state and send it; ``since``: when the change it answers arrived."""
        st = self._snapshot()
        cam = self.client.camera
        self._since = since
        if self.renderer.value == RENDERERS[1]:
            self._send_splats(st, cam)
        else:
            self._send_image(st, cam)

    def _send_image(self, st: ViewState, cam):
        if self._splat_t is not None:                 # back from the browser mode: drop the splats
            self._splats.remove()
            self._splat_t = None
        g = self.gentle()
        pose = (g.wxyz, g.position, float(cam.fov))
        res = self.model.view(pose, st, float(cam.aspect), self.tol)
        self.client.scene.set_background_image(res.image, format="jpeg", jpeg_quality=JPEG_QUALITY)
        self.last = res
        self._sent(res, st)

    def _send_splats(self, st: ViewState, cam):
        self.client.scene.set_background_image(None)
        if self._splat_t == st.t:
            return
        t0 = time.perf_counter()
        s = self.model.splats_at(st.t, np.asarray(cam.position))
        self._splats = self.client.scene.add_gaussian_splats("/gaussians", **s)
        self._splat_t = st.t
        self.last = None
        self.images_sent += 1
        self.status.content = (f"image {self.images_sent} · t = {st.t:.3f} · {len(s['centers'])} Gaussians "
                               f"sent to the browser in {(time.perf_counter() - t0) * 1e3:.0f} ms")

    def _sent(self, res: ViewResult, st: ViewState):
        now = time.perf_counter()
        if self._since is not None:          # recorded before the status line goes out (benchmarks read both)
            self.latencies_ms.append((now - self._since) * 1e3)
        self.images_sent += 1
        self.sent_times.append(now)
        fps = (len(self.sent_times) - 1) / (now - self.sent_times[0]) if len(self.sent_times) > 2 else 0.0
        h, w = res.image.shape[:2]
        where = ""
        if res.frame is not None:
            where = f" (frame {res.frame}, {self.model.frame_kind(res.frame)})"
        extra = ""
        if "psnr" in res.info:
            extra += f" · PSNR {res.info['psnr']:.2f} dB"
        if "depth_range" in res.info:
            lo, hi = res.info["depth_range"]
            extra += f" · depth {lo:.3g} (red) to {hi:.3g} (blue)"
        if res.frame is None and (st.show_gt or st.show_error or st.show_mask):
            extra += " · the side panes show at frame times (previous / next frame)"
        if self.orbit_deg >= 0.5:
            extra += (f" · turned {self.orbit_deg:.0f}° from frame {self.home_frame}'s camera "
                      f"(at most {ORBIT_MAX_DEG:.0f}°; 'frame camera' goes back)")
        if "flow_scale_px" in res.info:
            extra += f" · flow to the next frame, saturated at {res.info['flow_scale_px']:.2g} px"
        self.status.content = (f"image {self.images_sent} · t = {res.t:.3f}{where} · {w}x{h} · "
                               f"{res.render_ms:.0f} ms · {fps:.1f} img/s{extra}")

    def close(self):
        self.closed = True
        self.playing = False
        self.dirty.set()


class ViewerApp:
    """A viser server showing one loaded run."""

    def __init__(self, model: ViewerModel, host: str = "127.0.0.1", port: int = 8080, title: str = ""):
        self.model, self.host, self.port = model, host, int(port)
        self.title = title or "endowave-cl"
        self.sessions: Dict[int, Session] = {}
        self.server = None

    @property
    def url(self) -> str:
        host = "localhost" if self.host in ("0.0.0.0", "::", "") else self.host
        return f"http://{host}:{self.port}"

    def start(self):
        import viser
        problem = port_problem(self.host, self.port)
        if problem:
            raise EndowaveError(problem)
        # viser prints its own address banner unconditionally; we print one line of ours instead
        with contextlib.redirect_stdout(io.StringIO()):
            server = viser.ViserServer(host=self.host, port=self.port, label="endowave-cl", verbose=False)
        if server.get_port() != self.port:   # viser moves to the next free port; we promised this one
            server.stop()
            raise EndowaveError(f"port {self.port} is already in use on {self.host}; pick another with --port")
        self.server = server
        # the panel as a sidebar beside the image, not floating over it; no share button: it would
        # offer to publish the (possibly patient) video through viser's public tunnel
        server.gui.configure_theme(control_width="medium", show_share_button=False)
        server.gui.main_panel.dock_right()
        self._set_initial_camera(server)

        @server.on_client_connect
        def _(client):
            self.sessions[client.client_id] = Session(self, client)

        @server.on_client_disconnect
        def _(client):
            s = self.sessions.pop(client.client_id, None)
            if s is not None:
                s.close()
        return self

    def _set_initial_camera(self, server):
        """Every browser starts at the first frame's training camera, looking at the tissue; the
        orbit controls turn around the scene's up = the camera's up (-y in OpenCV)."""
        home = self.model.home_pose(0)
        focus = home["focus"]
        server.scene.set_up_direction(tuple(home["up"]))
        ic = server.initial_camera
        ic.position = tuple(home["position"])
        ic.look_at = tuple(home["look_at"])
        ic.up = tuple(home["up"])
        ic.fov = home["fov"]
        ic.near = max(1e-4, focus * 1e-3)
        ic.far = max(1e3, focus * 1e3)

    def stop(self):
        for s in list(self.sessions.values()):
            s.close()
        if self.server is not None:
            self.server.stop()
            self.server = None
