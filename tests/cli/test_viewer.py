"""The viewer's pure parts (endowave_cl/viewer.py): camera conversion, colour maps, pane layout,
the splats at a time.  No browser and no viser needed."""
from __future__ import annotations

import math
import socket

import numpy as np
import pytest


def _random_rotation(rng):
    q = rng.normal(size=4)
    from endowave_cl.viewer import quat_to_matrix
    return quat_to_matrix(q / np.linalg.norm(q))


def test_camera_round_trip_through_browser_pose():
    """Our camera -> the browser's (wxyz, position, fov) -> our camera gives the same view."""
    from endowave_cl.camera import Camera
    from endowave_cl.viewer import camera_from_pose, pose_of_camera
    rng = np.random.default_rng(0)
    for _ in range(5):
        R = _random_rotation(rng)
        t = rng.normal(size=3)
        view = np.eye(4)
        view[:3, :3], view[:3, 3] = R, t
        cam = Camera(200.0, 200.0, 80.0, 64.0, 160, 128, view)
        wxyz, pos, fov = pose_of_camera(cam)
        back = camera_from_pose(wxyz, pos, fov, 160, 128)
        np.testing.assert_allclose(back.viewmat, cam.viewmat, atol=1e-5)
        assert back.fy == pytest.approx(200.0, rel=1e-6) and back.fx == back.fy
        assert (back.cx, back.cy) == (80.0, 64.0)
        # a point in front of the camera projects to the same pixel
        p = cam.campos + 3.0 * R.T[:, 2] + 0.2 * R.T[:, 0]

        def pixel(c):
            pc = c.viewmat[:3, :3] @ p + c.viewmat[:3, 3]
            return np.array([c.fx * pc[0] / pc[2] + c.cx, c.fy * pc[1] / pc[2] + c.cy])
        np.testing.assert_allclose(pixel(back), pixel(cam), atol=1e-3)


def test_render_size_follows_aspect():
    from endowave_cl.viewer import render_size
    assert render_size(256, 1.25) == (320, 256)
    assert render_size(512, 1.25) == (640, 512)
    assert render_size(256, float("nan")) == (256, 256)


def test_flow_wheel_direction_and_saturation():
    from endowave_cl.viewer import flow_image
    flow = np.zeros((2, 3, 2), np.float32)
    flow[0, 0] = (4, 0)      # right, saturated
    flow[0, 1] = (-4, 0)     # left, saturated
    flow[0, 2] = (1, 0)      # right, a quarter
    alpha = np.ones((2, 3), np.float32)
    alpha[1, 2] = 0.0        # uncovered
    img = flow_image(flow, alpha, scale=4.0).astype(int)
    assert tuple(img[1, 0]) == (255, 255, 255)               # no motion: white
    assert tuple(img[1, 2]) == (0, 0, 0)                     # uncovered: black
    assert img[0, 0, 0] == 255 and img[0, 0, 1] < 10 and img[0, 0, 2] < 10     # hue 0: red
    assert img[0, 1, 0] < 10 and img[0, 1, 1] > 240 and img[0, 1, 2] > 240     # opposite: cyan
    assert 150 < img[0, 2, 1] < 230                          # a quarter of the way from white to red


def test_depth_map_near_red_far_blue():
    from endowave_cl.viewer import depth_image, depth_range
    alpha = np.ones((1, 3), np.float32)
    depth = np.array([[1.0, 2.0, 3.0]], np.float32)
    lo, hi = depth_range(depth, alpha)
    assert 1.0 <= lo < 1.1 and 2.9 < hi <= 3.0
    img = depth_image(depth, alpha, 1.0, 3.0).astype(int)
    assert img[0, 0, 0] > img[0, 0, 2] and img[0, 2, 2] > img[0, 2, 0]
    # depth is divided by alpha: a half-covered pixel at accumulated depth 1 means depth 2
    img2 = depth_image(np.array([[1.0]], np.float32), np.array([[0.5]], np.float32), 1.0, 3.0)
    np.testing.assert_array_equal(img2[0, 0], img[0, 1])


def test_compose_grid_main_top_left_then_side_panes():
    from endowave_cl.viewer import PANE_GAP, compose, pane_size
    W, H = 320, 256
    assert pane_size(W, H, 0) == (W, H)
    pw, ph = pane_size(W, H, 2)
    assert (pw, ph) == ((W - PANE_GAP) // 2, (H - PANE_GAP) // 2)
    main = np.full((ph, pw, 3), 200, np.uint8)
    gt = np.full((48, 64, 3), 50, np.uint8)
    err = np.full((48, 64, 3), 90, np.uint8)
    out = compose(main, [("a", gt), ("b", err)], W, H)
    assert out.shape == (H, W, 3)
    assert (out[:ph, :pw] == 200).all()
    assert (out[:, pw:pw + PANE_GAP] == 0).all() and (out[ph:ph + PANE_GAP] == 0).all()
    assert (out[ph // 2, pw + PANE_GAP + 5:] == 50).any()               # top right: the first side pane
    assert (out[ph + PANE_GAP + ph // 2, :pw] == 90).any()              # bottom left: the second
    assert (out[ph + PANE_GAP:, pw + PANE_GAP:] == 0).all()             # bottom right: empty
    assert compose(main, [], pw, ph) is main


def test_error_image_ignores_tool_pixels():
    from endowave_cl.viewer import error_image
    gt = np.zeros((1, 2, 3), np.float32)
    pred = np.full((1, 2, 3), 0.25, np.float32)
    e = error_image(pred, gt, np.array([[1.0, 0.0]], np.float32))
    assert e[0, 0].sum() > 600 and e[0, 1].sum() < 30       # saturated vs the map's black end


def test_port_free_sees_a_listening_socket():
    from endowave_cl.viewer_app import port_free
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        assert not port_free("127.0.0.1", port)
    assert port_free("127.0.0.1", port)
    from endowave_cl.viewer_app import port_problem
    assert "cannot resolve" in port_problem("no-such-host.invalid", port)


def test_slider_marks_label_a_few_frames():
    from endowave_cl.viewer_app import MAX_MARK_LABELS, _marks
    times = np.linspace(0, 1, 63)
    marks = _marks(times)
    assert len(marks) == 63
    labelled = [m for m in marks if isinstance(m, tuple)]
    assert 2 <= len(labelled) <= MAX_MARK_LABELS + 1 and labelled[-1] == (1.0, "62")


def test_splats_at_time_match_the_ply_export(tmp_path):
    """The browser mode's Gaussians are export_ply's at t, with colour evaluated like the kernel."""
    from endowave_cl.export_ply import gaussians_at
    from endowave_cl.gaussians import Gaussians
    from endowave_cl.viewer import ViewerModel

    g = Gaussians.random(200, seed=1)
    g.means[:, 3] = 0.5
    model = ViewerModel.__new__(ViewerModel)   # splats_at needs only the Gaussians, not a device
    model.gaussians = g
    s = model.splats_at(0.5, np.zeros(3))
    a = gaussians_at(g, 0.5)
    M = len(a["mean"])
    assert M > 0 and s["centers"].shape == (M, 3) and s["covariances"].shape == (M, 3, 3)
    np.testing.assert_allclose(s["centers"], a["mean"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(s["opacities"][:, 0], a["opacity"], rtol=1e-5)
    np.testing.assert_allclose(s["covariances"], a["cov"], rtol=1e-4, atol=1e-6)
    assert (s["rgbs"] >= 0).all() and (s["rgbs"] <= 1).all()
    # colour: 0.5 + sum_k c_k Y_k(d); the DC term alone for a Gaussian seen along any direction
    import torch
    from endowave_cl.reference.project import teash_colour
    keep = a["keep"]
    d = a["mean"] / np.linalg.norm(a["mean"], axis=1, keepdims=True)
    ref = teash_colour(torch.from_numpy(g.sh[keep].astype(np.float64)),
                       torch.from_numpy(g.phase[keep].astype(np.float64)), torch.from_numpy(d), 0.5).numpy()
    np.testing.assert_allclose(s["rgbs"], np.clip(ref, 0, 1), atol=1e-5)
    assert math.isfinite(float(s["covariances"].sum()))


def test_numpy_sh_basis_matches_the_reference():
    import torch
    from endowave_cl.reference.project import sh_basis
    from endowave_cl.viewer import sh_basis_np
    d = np.random.default_rng(2).normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for deg in range(4):
        np.testing.assert_allclose(sh_basis_np(d, deg), sh_basis(torch.from_numpy(d), deg).numpy(), atol=1e-12)


# ---------------------------------------------------------------------------------------------
# the gentle orbit and the way back to the frame camera

def _orbit(wxyz, position, look_at, up, ang):
    """The browser camera after viser's orbit controls turn it by ``ang`` radians about ``up``
    through ``look_at`` (camera-controls' azimuth: 2 pi * drag px / canvas height)."""
    from endowave_cl.viewer import _rotation, matrix_to_quat, quat_to_matrix
    Q = _rotation(np.asarray(up, np.float64) / np.linalg.norm(up), ang)
    R = Q @ quat_to_matrix(wxyz)
    return matrix_to_quat(R), look_at + Q @ (np.asarray(position) - look_at)


def _home_camera():
    from endowave_cl.camera import Camera
    from endowave_cl.viewer import pose_of_camera, quat_to_matrix
    R = _random_rotation(np.random.default_rng(7))
    view = np.eye(4)
    view[:3, :3], view[:3, 3] = R, (0.3, -0.2, 0.1)
    cam = Camera(100.0, 100.0, 40.0, 32.0, 80, 64, view)
    wxyz, pos, _ = pose_of_camera(cam)
    Rw = quat_to_matrix(wxyz)
    return wxyz, pos, pos + 5.0 * Rw[:, 2], -Rw[:, 1]


def _deg_between(a_wxyz, b_wxyz):
    from endowave_cl.viewer import quat_to_matrix
    f = quat_to_matrix(a_wxyz)[:, 2] @ quat_to_matrix(b_wxyz)[:, 2]
    return math.degrees(math.acos(float(np.clip(f, -1, 1))))


@pytest.mark.parametrize("canvas_h", [400, 800, 1200])
def test_a_120px_drag_turns_the_view_gently(canvas_h):
    """120 px of drag turns viser's camera 2 pi * 120 / canvas height (54 degrees at 800 px, a
    grazing view of tissue seen head-on); the rendered view turns ORBIT_SENSITIVITY of that, never
    more than ORBIT_MAX_DEG, around the same orbit point at the same distance."""
    from endowave_cl.viewer import ORBIT_MAX_DEG, ORBIT_SENSITIVITY, gentle_pose, quat_to_matrix
    assert ORBIT_SENSITIVITY == 0.25 and ORBIT_MAX_DEG == 30.0          # the numbers the docstring states
    wxyz, pos, look_at, up = _home_camera()
    raw = 2 * math.pi * 120 / canvas_h
    b_wxyz, b_pos = _orbit(wxyz, pos, look_at, up, raw)
    g = gentle_pose(b_wxyz, b_pos, look_at, wxyz)
    turned = _deg_between(g.wxyz, wxyz)
    assert g.raw_deg == pytest.approx(math.degrees(raw), abs=1e-6)
    assert turned == pytest.approx(min(0.25 * math.degrees(raw), 30.0), abs=1e-6) and turned <= 30.0 + 1e-9
    assert g.deg == pytest.approx(turned, abs=1e-6)
    np.testing.assert_allclose(np.linalg.norm(g.position - look_at), 5.0, rtol=1e-9)   # same distance
    np.testing.assert_allclose(g.position + 5.0 * quat_to_matrix(g.wxyz)[:, 2], look_at, atol=1e-9)
    if canvas_h == 800:
        assert turned == pytest.approx(13.5, abs=1e-6)


def test_without_a_turn_pan_and_zoom_pass_through():
    from endowave_cl.viewer import gentle_pose, quat_to_matrix
    wxyz, pos, look_at, up = _home_camera()
    R = quat_to_matrix(wxyz)
    shift = 0.4 * R[:, 0] - 0.1 * R[:, 1]
    zoomed = pos + 2.0 * R[:, 2] + shift            # dolly in by 2, pan
    g = gentle_pose(wxyz, zoomed, look_at + shift, wxyz)
    np.testing.assert_allclose(g.position, zoomed, atol=1e-9)
    assert _deg_between(g.wxyz, wxyz) < 1e-6 and g.limit_position is None


def test_past_the_clamp_the_browser_camera_is_pulled_back():
    """Beyond ORBIT_MAX_DEG / ORBIT_SENSITIVITY = 120 degrees (+1 slack) of browser turn nothing
    changes on screen: limit_position puts the browser camera back at exactly 120 degrees."""
    from endowave_cl.viewer import gentle_pose
    wxyz, pos, look_at, up = _home_camera()
    g = gentle_pose(*_orbit(wxyz, pos, look_at, up, math.radians(119.0)), look_at, wxyz)
    assert g.limit_position is None and g.deg == pytest.approx(29.75)
    g = gentle_pose(*_orbit(wxyz, pos, look_at, up, math.radians(150.0)), look_at, wxyz)
    assert g.deg == pytest.approx(30.0)
    _, want = _orbit(wxyz, pos, look_at, up, math.radians(120.0))
    np.testing.assert_allclose(g.limit_position, want, atol=1e-9)


class _FakeCamera:
    """viser's CameraHandle as far as the session uses it (setting position moves look_at along)."""

    def __init__(self, wxyz, position, look_at, up, fov=0.8):
        self.wxyz, self.position, self.look_at = np.asarray(wxyz), np.asarray(position), np.asarray(look_at)
        self.up_direction, self.fov, self.aspect = np.asarray(up), fov, 1.25

    def browser_moved(self, wxyz, position, look_at=None):
        """A camera message from the browser: its state as it is, no setter side effects."""
        object.__setattr__(self, "wxyz", np.asarray(wxyz))
        object.__setattr__(self, "position", np.asarray(position))
        if look_at is not None:
            object.__setattr__(self, "look_at", np.asarray(look_at))

    def __setattr__(self, k, v):
        if k == "position" and "position" in self.__dict__:
            v = np.asarray(v, np.float64)
            object.__setattr__(self, "look_at", self.look_at + v - self.position)
        object.__setattr__(self, k, np.asarray(v, np.float64) if k != "fov" else v)
        if k in ("position", "look_at") and "look_at" in self.__dict__ and "up_direction" in self.__dict__:
            from endowave_cl.viewer import matrix_to_quat     # what viser's _update_wxyz computes
            z = self.look_at - self.position
            z = z / np.linalg.norm(z)
            y = -(self.up_direction - (self.up_direction @ z) * z)
            y = y / np.linalg.norm(y)
            object.__setattr__(self, "wxyz", matrix_to_quat(np.stack([np.cross(y, z), y, z], 1)))


def _session_on_two_frames():
    """A viewer_app.Session without viser: a model of two frames whose cameras differ, a fake
    client camera at frame 0's camera."""
    import threading
    import types

    from endowave_cl.camera import Camera
    from endowave_cl.gaussians import Gaussians
    from endowave_cl.viewer import ViewerModel, quat_to_matrix
    from endowave_cl.viewer_app import Session

    def cam(tx):
        view = np.eye(4)
        view[:3, 3] = (tx, 0.0, 0.0)
        return Camera(100.0, 100.0, 40.0, 32.0, 80, 64, view)
    model = ViewerModel.__new__(ViewerModel)
    model.scene = types.SimpleNamespace(frames=[types.SimpleNamespace(camera=cam(0.0), time=0.0),
                                                types.SimpleNamespace(camera=cam(-0.5), time=1.0)])
    model.times = np.array([0.0, 1.0])
    g = Gaussians.random(300, seed=0)
    g.means[:, :3] = np.random.default_rng(0).normal(size=(300, 3)) * 0.2 + (0, 0, 4.0)   # tissue at z ~ 4
    model.gaussians = g
    s = Session.__new__(Session)
    s.model, s.dirty, s.pending_since, s.have_camera = model, threading.Event(), None, True
    h0 = model.home_pose(0)
    s.home_frame, s.home_wxyz, s.orbit_deg = 0, h0["wxyz"], 0.0
    s.client = types.SimpleNamespace(camera=_FakeCamera(h0["wxyz"], h0["position"], h0["look_at"], h0["up"]))
    s.time = types.SimpleNamespace(value=0.0)
    assert quat_to_matrix(h0["wxyz"])[:, 2] @ (0, 0, 1) > 0.999 and 3.5 < h0["focus"] < 4.5
    return s, model


def test_frame_camera_button_restores_the_training_camera_of_the_current_frame():
    from endowave_cl.viewer import pose_of_camera
    s, model = _session_on_two_frames()
    c = s.client.camera
    w, p = _orbit(c.wxyz, c.position, c.look_at, c.up_direction, 1.2)           # a wild drag ...
    c.browser_moved(w, p + 0.3, c.look_at + 0.3)                                  # ... and a pan
    c.fov = 1.3
    s.time.value = 0.9                         # the slider nearest frame 1
    s.back_to_frame_camera()
    wxyz, pos, fov = pose_of_camera(model.scene.frames[1].camera)
    np.testing.assert_allclose(c.position, pos, atol=1e-9)
    assert _deg_between(c.wxyz, wxyz) < 1e-6 and c.fov == pytest.approx(fov)
    np.testing.assert_allclose(c.look_at, model.home_pose(1)["look_at"], atol=1e-9)
    assert s.home_frame == 1 and s.dirty.is_set()
    g = s.gentle()                             # and the view rendered from there is that camera
    np.testing.assert_allclose(g.position, pos, atol=1e-9)
    assert g.deg < 1e-6


def test_session_renders_the_gentle_view_and_pulls_the_browser_back():
    s, _ = _session_on_two_frames()
    c = s.client.camera
    home_wxyz = s.home_wxyz
    c.browser_moved(*_orbit(c.wxyz, c.position, c.look_at, c.up_direction, 2 * math.pi * 120 / 800))
    g = s.gentle()
    assert _deg_between(g.wxyz, home_wxyz) == pytest.approx(13.5, abs=1e-3)
    c.browser_moved(*_orbit(c.wxyz, c.position, c.look_at, c.up_direction, math.radians(100.0)))
    g = s.gentle()                             # 154 degrees of browser turn: 30 on screen, pulled back to 120
    assert g.deg == pytest.approx(30.0)
    assert _deg_between(c.wxyz, home_wxyz) == pytest.approx(120.0, abs=1e-3)
