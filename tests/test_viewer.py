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
