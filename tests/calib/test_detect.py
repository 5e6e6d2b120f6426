"""Board detection on rendered images with exactly known corners."""

from __future__ import annotations

import cv2
import numpy as np
from plantscan_calib.detect import (
    BoardSpec,
    detect_charuco,
    detect_chessboard,
    detect_chessboard_plain,
)
from plantscan_calib.synthetic import board_texture, render_board_view

from plantscan_core.data import Camera, CameraModel, Pose, rotation_x, rotation_z


def _view(size=(2400, 1600), yaw=15.0, spec=None):
    spec = spec or BoardSpec("chessboard", 9, 6, 25.0)
    w, h = size
    cam = Camera(CameraModel(1.1 * w, (w - 1) / 2, (h - 1) / 2, width=w, height=h),
                 Pose.look_at((0.0, -600.0, 150.0), (0.0, 0.0, 120.0)))
    r = rotation_z(yaw) @ rotation_x(-100.0)
    board = Pose(r, np.array([0.0, 0.0, 120.0]) - r @ spec.object_points().mean(axis=0))
    tex, margin = board_texture(spec, 12.0)
    img = render_board_view(cam, board, spec, tex, 12.0, margin, supersample=4)
    truth = cam.project(spec.object_points() @ board.R.T + board.t)
    return img, truth, spec


def test_pyramid_detection_is_subpixel_accurate():
    img, truth, spec = _view()
    uv = detect_chessboard(img, spec.cols, spec.rows, max_side_px=800)
    assert uv is not None
    # Corner 0 is the same physical corner as the renderer's (no flip) and every corner
    # lies within 0.15 px of the exact projection (homography render, area filter).
    err = np.linalg.norm(uv - truth, axis=1)
    assert err.max() < 0.15, err.max()


def test_pyramid_matches_plain_full_resolution_detection():
    img, truth, spec = _view()
    a = detect_chessboard(img, spec.cols, spec.rows, max_side_px=800)
    b = detect_chessboard_plain(img, spec.cols, spec.rows)
    assert np.abs(a - b).max() < 0.1


def test_order_is_canonical_when_the_view_turns_upside_down():
    # An asymmetric board (9+6 odd) turned by 180 degrees in the image keeps its numbering.
    img, truth, spec = _view(yaw=10.0)
    turned = img[::-1, ::-1].copy()
    h, w = img.shape
    uv = detect_chessboard(turned, spec.cols, spec.rows, max_side_px=800)
    expected = np.stack([w - 1 - truth[:, 0], h - 1 - truth[:, 1]], axis=1)
    assert np.linalg.norm(uv - expected, axis=1).max() < 0.2


def test_no_board_gives_none():
    rng = np.random.default_rng(0)
    img = rng.integers(100, 140, (1600, 2400), dtype=np.uint8)
    assert detect_chessboard(img, 9, 6) is None


def test_charuco_ids_and_positions():
    spec = BoardSpec("charuco", 9, 6, 25.0, 18.0, "DICT_5X5_100")
    board = spec.charuco_board()
    ppm = 10.0
    tex = board.generateImage((int(10 * 25 * ppm), int(7 * 25 * ppm)))
    w, h = 1800, 1200
    cam = Camera(CameraModel(1.1 * w, (w - 1) / 2, (h - 1) / 2, width=w, height=h),
                 Pose.look_at((0.0, -500.0, 150.0), (0.0, 0.0, 120.0)))
    r = rotation_z(20.0) @ rotation_x(-100.0)
    pose = Pose(r, np.array([0.0, 0.0, 120.0]) - r @ spec.object_points().mean(axis=0))
    # texture pixel centre (u, v) -> board mm with inner corner 0 at the origin
    big = cam.model.scaled(4)  # render 4x finer, then area-average (anti-aliasing)
    hmat = big.K @ np.column_stack([(cam.pose.R @ r)[:, 0], (cam.pose.R @ r)[:, 1],
                                    cam.pose.R @ pose.t + cam.pose.t])
    h_tex = np.array([[1 / ppm, 0, 0.5 / ppm - 25.0], [0, 1 / ppm, 0.5 / ppm - 25.0], [0, 0, 1]])
    img = cv2.warpPerspective(tex, hmat @ h_tex, (big.width, big.height), flags=cv2.INTER_LINEAR,
                              borderValue=200)
    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    hit = detect_charuco(img, spec)
    assert hit is not None
    ids, uv = hit
    assert len(ids) >= 40
    truth = cam.project(spec.object_points()[ids] @ pose.R.T + pose.t)
    assert np.linalg.norm(uv - truth, axis=1).max() < 0.2
