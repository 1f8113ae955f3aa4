"""The blurred X-junction fit of chessboard corners (frontend/fpp/corner_refinement.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fpp_graph.errors import CalibrationError
from frontend.fpp.calibration_board import Chessboard, find_chessboard
from frontend.fpp.corner_refinement import (
    MAX_HALF_WINDOW_PX,
    MIN_HALF_WINDOW_PX,
    fit_corner_model,
    half_window_px,
)


def render_board(H: np.ndarray, board: Chessboard, size=(320, 260), samples=8, blur_px=0.8, noise_grey=0.0, seed=0):
    """A chessboard seen through the homography ``H`` (board squares -> pixels): every pixel
    averages ``samples**2`` point samples of the board (a sensor pixel's area), then Gaussian
    blur and noise. Returns the image (float) and the true corners (x fastest)."""
    W, Hh = size
    offsets = (np.arange(samples) + 0.5) / samples - 0.5
    v, u = np.mgrid[0:Hh, 0:W].astype(np.float64)
    Hinv = np.linalg.inv(H)
    acc = np.zeros((Hh, W))
    nx, ny = board.corners
    for dy in offsets:
        for dx in offsets:
            q = np.stack([u + dx, v + dy, np.ones_like(u)], axis=-1) @ Hinv.T
            bx, by = q[..., 0] / q[..., 2], q[..., 1] / q[..., 2]
            inside = (bx > -1) & (bx < nx) & (by > -1) & (by < ny)
            black = (np.floor(bx) + np.floor(by)) % 2 == 0
            acc += np.where(inside, np.where(black, 25.0, 215.0), 215.0)
    img = cv2.GaussianBlur(acc / samples**2, (0, 0), blur_px)
    img = img + np.random.default_rng(seed).normal(0.0, noise_grey, img.shape)
    gx, gy = np.meshgrid(np.arange(nx), np.arange(ny))
    corners = np.column_stack([gx.ravel(), gy.ravel(), np.ones(nx * ny)]) @ H.T
    return img, corners[:, :2] / corners[:, 2:3]


def tilted_view(scale=34.0, angle_deg=17.0, perspective=(4e-4, -3e-4), offset=(61.3, 48.7)):
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    H = np.array([[scale * c, -scale * s * 0.8, offset[0]], [scale * s, scale * c * 0.9, offset[1]], [perspective[0], perspective[1], 1.0]])
    return H


def corner_errors(image: np.ndarray, board: Chessboard, truth: np.ndarray, model_fit: bool) -> np.ndarray:
    found = find_chessboard(np.clip(np.rint(image), 0, 255).astype(np.uint8), board, model_fit=model_fit)
    assert found is not None
    return np.linalg.norm(found - truth, axis=1)


@pytest.mark.parametrize("noise_grey", [0.0, 1.0])
def test_model_fit_finds_corners_of_a_tilted_board_to_a_hundredth_of_a_pixel(noise_grey):
    """An area-integrated, blurred, perspective view: cornerSubPix lands a few hundredths of a
    pixel off, the X-junction fit within 0.01 px RMS (8-bit quantisation included)."""
    board = Chessboard((6, 5), 0.02)
    image, truth = render_board(tilted_view(), board, noise_grey=noise_grey)
    subpix = corner_errors(image, board, truth, model_fit=False)
    model = corner_errors(image, board, truth, model_fit=True)
    assert np.sqrt(np.mean(model**2)) < 0.01
    assert np.sqrt(np.mean(model**2)) < 0.5 * np.sqrt(np.mean(subpix**2))


def test_a_corner_under_a_glare_spot_keeps_its_start_and_is_counted(caplog):
    """A saturated blob over one corner: the model cannot explain its window, so that corner
    keeps the position it started from (and the count is logged); the others are refined."""
    board = Chessboard((6, 5), 0.02)
    image, truth = render_board(tilted_view(), board)
    start = truth + np.random.default_rng(1).normal(0.0, 0.05, truth.shape)
    glare_at = truth[8]
    v, u = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    image = np.where((u - glare_at[0] - 2.0) ** 2 + (v - glare_at[1] + 1.0) ** 2 < 5.0**2, 255.0, image)
    with caplog.at_level("INFO", logger="frontend.fpp.corner_refinement"):
        refined, fitted = fit_corner_model(image, start, board.corners)
    assert not fitted[8]
    np.testing.assert_array_equal(refined[8], start[8])
    assert fitted.sum() == len(fitted) - 1
    others = np.delete(np.linalg.norm(refined - truth, axis=1), 8)
    assert np.sqrt(np.mean(others**2)) < 0.01
    assert "1 of 30 corners kept cornerSubPix's position" in caplog.text


def test_window_is_a_quarter_of_the_corner_spacing_within_bounds():
    board = (3, 2)
    grid = np.array([[x, y] for y in range(2) for x in range(3)], dtype=float)
    assert half_window_px(grid * 40.0, board) == 10
    assert half_window_px(grid * 400.0, board) == MAX_HALF_WINDOW_PX
    assert half_window_px(grid * 6.0, board) == MIN_HALF_WINDOW_PX


def test_undecoded_pixels_in_a_texture_take_no_part():
    """A decoded texture (the corners' image when a pattern set has no white image) is NaN where
    decoding failed: those pixels are left out of the fit, the corner is still refined."""
    board = Chessboard((6, 5), 0.02)
    image, truth = render_board(tilted_view(), board)
    start = truth + np.random.default_rng(2).normal(0.0, 0.05, truth.shape)
    v, u = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    holed = np.where((u - truth[8, 0] - 6.0) ** 2 + (v - truth[8, 1]) ** 2 < 3.0**2, np.nan, image)
    refined, fitted = fit_corner_model(holed, start, board.corners)
    assert fitted.all()
    assert np.linalg.norm(refined[8] - truth[8]) < 0.03  # 0.015 px: the hole breaks the window's symmetry


def test_corners_that_are_not_the_boards_grid_are_refused():
    board = Chessboard((6, 5), 0.02)
    image, truth = render_board(tilted_view(), board)
    with pytest.raises(CalibrationError, match=r"6x5 = 30 corners .* got an image of shape \(260, 320\) and 29 corners"):
        fit_corner_model(image, truth[:-1], board.corners)
    with pytest.raises(CalibrationError, match="grey"):
        fit_corner_model(np.dstack([image] * 3), truth, board.corners)
