"""SURF (frontend.features.surf) and the feature factory/matching (frontend.features.detect)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fpp_graph.errors import InputDataError
from fpp_graph.types import Frame
from frontend.config import RegistrationConfig
from frontend.features.detect import detect_and_describe, make_detector, match_descriptors
from frontend.features.surf import (
    SurfParams,
    hessian_layer,
    hessian_layer_dense,
    surf_detect_and_compute,
)


def _texture(seed: int = 0, shape=(240, 320)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 2.5)
    img = (img - img.min()) / (img.max() - img.min())
    return np.clip(img * 255, 0, 255).astype(np.uint8)


def test_dense_and_integral_hessian_agree():
    img = _texture(1).astype(np.float32) / 255
    pad = 40
    ii = cv2.integral(cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_REPLICATE), sdepth=cv2.CV_64F)
    for L in (9, 15, 27):
        a, sa = hessian_layer(ii, pad, 1, img.shape[0], img.shape[1], L)
        b, sb = hessian_layer_dense(img, L)
        inner = (slice(20, -20), slice(20, -20))
        assert np.abs(a - b)[inner].max() < 1e-6 * np.abs(a[inner]).max()


def test_blob_position_and_scale():
    # a Gaussian blob of sigma 4 px: SURF's scale s relates to sigma (s ~ sigma / sqrt(2) .. sigma)
    img = np.full((160, 200), 40, np.uint8)
    yy, xx = np.mgrid[0:160, 0:200]
    blob = 200 * np.exp(-((xx - 97.3) ** 2 + (yy - 81.6) ** 2) / (2 * 4.0**2))
    img = np.clip(img + blob, 0, 255).astype(np.uint8)
    kp = surf_detect_and_compute(img, SurfParams(hessian_threshold=1e-3))
    assert len(kp) >= 1
    best = int(np.argmax(kp.response))
    assert np.allclose(kp.uv[best], [97.3, 81.6], atol=0.5)
    assert 2.0 < kp.scale[best] < 6.0
    assert kp.laplacian_sign[best] == -1  # bright blob: negative trace
    assert np.allclose(np.linalg.norm(kp.descriptors, axis=1), 1.0, atol=1e-5)


def test_rotation_invariant_matching():
    img = _texture(2)
    M = cv2.getRotationMatrix2D((160, 120), 35, 1.0)
    rot = cv2.warpAffine(img, M, (320, 240), borderMode=cv2.BORDER_REFLECT)
    a = surf_detect_and_compute(img)
    b = surf_detect_and_compute(rot)
    m = match_descriptors(a.descriptors, b.descriptors, 0.8, True)
    assert m.shape[0] > 40
    pred = a.uv[m[:, 0]] @ M[:, :2].T + M[:, 2]
    err = np.linalg.norm(pred - b.uv[m[:, 1]], axis=1)
    assert np.mean(err < 1.5) > 0.8
    assert np.median(err[err < 1.5]) < 0.5


def test_working_width_maps_back_to_full_pixels():
    img = _texture(3, (240, 320))
    big = cv2.resize(img, (640, 480), interpolation=cv2.INTER_LINEAR)
    small_kp = surf_detect_and_compute(img, SurfParams(max_working_width=0))
    big_kp = surf_detect_and_compute(big, SurfParams(max_working_width=320))
    m = match_descriptors(small_kp.descriptors, big_kp.descriptors, 0.8, True)
    pred = (small_kp.uv[m[:, 0]] + 0.5) * 2 - 0.5
    err = np.linalg.norm(pred - big_kp.uv[m[:, 1]], axis=1)
    assert np.median(err) < 1.0


def test_surf_rejects_bad_images():
    with pytest.raises(InputDataError, match="uint8"):
        surf_detect_and_compute(np.zeros((64, 64), np.float32))
    with pytest.raises(InputDataError, match="at least 32x32"):
        surf_detect_and_compute(np.zeros((16, 64), np.uint8))
    assert len(surf_detect_and_compute(np.zeros((64, 64), np.uint8))) == 0  # flat: no keypoints, no error


@pytest.mark.parametrize("feature", ["surf", "sift", "orb", "akaze"])
def test_detector_factory(feature):
    img = _texture(4)
    cfg = RegistrationConfig(features={"type": feature, "max_features": 300})
    uv, desc = make_detector(cfg)(img)
    assert uv.shape[0] == desc.shape[0] > 20
    assert uv.shape[0] <= 300 or feature == "akaze"
    assert np.all((uv >= -0.5) & (uv <= [319.5, 239.5]))
    assert desc.dtype == (np.float32 if feature in ("surf", "sift") else np.uint8)


def test_detect_and_describe_and_missing_texture():
    frame = Frame(id=3, timestamp=0.0, points=np.zeros((0, 3)), texture=_texture(5))
    out = detect_and_describe(frame, RegistrationConfig())
    assert out.keypoints_uv.shape[0] > 20 and out.metadata["feature"] == "surf"
    with pytest.raises(InputDataError, match="frame 4: no texture"):
        detect_and_describe(Frame(id=4, timestamp=0.0, points=np.zeros((0, 3))), RegistrationConfig())


def test_match_ratio_and_mutual():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(50, 64)).astype(np.float32)
    b = np.concatenate([a[:30] + 0.01 * rng.normal(size=(30, 64)).astype(np.float32), rng.normal(size=(20, 64)).astype(np.float32)])
    m = match_descriptors(a, b, 0.8, True)
    assert set(map(tuple, m)) == {(i, i) for i in range(30)}
    with pytest.raises(InputDataError, match="same feature type"):
        match_descriptors(a, b.astype(np.uint8), 0.8, True)
    assert match_descriptors(a[:1], b, 0.8, True).shape == (0, 2)


def test_block_sums_equal_area_averaging():
    from frontend.features.surf import block_sums

    img = _texture(6, (240, 320))
    sums = block_sums(img, 2)
    assert sums.dtype == np.uint16 and sums.shape == (120, 160)
    area = cv2.resize(img.astype(np.float32), (160, 120), interpolation=cv2.INTER_AREA)
    assert np.allclose(sums / 4.0, area, atol=1e-4)
    assert block_sums(img, 1) is img


def test_integer_working_image_gives_the_float_responses():
    # fast_hessian on exact integer block sums (value_scale) must equal it on the [0, 1] image
    from frontend.features.surf import block_sums, fast_hessian

    img = _texture(7, (240, 320))
    ints = block_sums(img, 2)
    floats = ints.astype(np.float32) / np.float32(4 * 255)
    p = SurfParams(hessian_threshold=1e-4)
    a = fast_hessian(floats, p)
    b = fast_hessian(ints, p, value_scale=1.0 / (4 * 255))
    assert a[0].shape == b[0].shape and a[0].shape[0] > 10
    assert np.allclose(a[0], b[0], atol=1e-3)
    assert np.allclose(a[2], b[2], rtol=1e-4)
    assert np.array_equal(a[3], b[3])


def test_haar_bank_matches_box_sums_at_pixels():
    # dx = (right half - left half) of a 2h x 2h window centred between pixels, read by remap
    from frontend.features.surf_descriptors import HaarBank

    img = _texture(8, (120, 160)).astype(np.float32)
    bank = HaarBank(img)
    ii = cv2.integral(img, sdepth=cv2.CV_64F)

    def box(y0, y1, x0, x1):  # rows y0..y1-1, cols x0..x1-1
        return ii[y1, x1] - ii[y0, x1] - ii[y1, x0] + ii[y0, x0]

    # sides 4 and 6 are read on the image itself; side 8 on the half-resolution level, whose
    # (area-averaged) box sums are a quarter of the image's for windows on even pixel bounds
    for half, unit in ((2, 1.0), (3, 1.0), (4, 0.25)):
        # a window of side 2h centred at pixel-centre coordinate c covers pixels c-h+0.5 .. c+h-0.5
        for cx, cy in ((59.5, 49.5), (71.5, 41.5), (80.0, 60.0)):
            x0, y0 = int(round(cx - half + 0.5)), int(round(cy - half + 0.5))
            if abs((cx - half + 0.5) - x0) > 1e-9 or abs((cy - half + 0.5) - y0) > 1e-9:
                continue  # only windows aligned with pixels have an exact box sum
            dx_ref = unit * (box(y0, y0 + 2 * half, x0 + half, x0 + 2 * half) - box(y0, y0 + 2 * half, x0, x0 + half))
            dy_ref = unit * (box(y0 + half, y0 + 2 * half, x0, x0 + 2 * half) - box(y0, y0 + half, x0, x0 + 2 * half))
            dx, dy = bank.sample(2.0 * half, np.array([[cx]]), np.array([[cy]]))
            assert abs(dx[0, 0] - dx_ref) < 1e-3 * max(1.0, abs(dx_ref)), (half, cx, cy)
            assert abs(dy[0, 0] - dy_ref) < 1e-3 * max(1.0, abs(dy_ref)), (half, cx, cy)


def test_l2_nearest_matches_brute_force_with_ties_and_chunks():
    # the column nearest neighbours come from the column minima and the first row holding them
    from frontend.features.detect import l2_nearest

    rng = np.random.default_rng(9)
    a = rng.normal(size=(70, 8)).astype(np.float32)
    b = rng.normal(size=(90, 8)).astype(np.float32)
    b[:6] = a[:6]  # exact matches
    a[10] = a[11]  # two rows equally near every column: the first must win
    D = ((a[:, None, :].astype(np.float64) - b[None, :, :]) ** 2).sum(axis=2)
    for chunk in (2048, 16):
        ia, ib, score, nn_ba = l2_nearest(a, b, 0.9, chunk_rows=chunk)
        assert np.array_equal(nn_ba, np.argmin(D, axis=0))
        assert np.array_equal(ib, np.argmin(D, axis=1)[ia])
        srt = np.sort(D, axis=1)
        np.testing.assert_allclose(score, np.sqrt(srt[ia, 0] / srt[ia, 1]), atol=1e-3)
        assert set(range(6)) <= set(ia.tolist())


def test_integer_integral_gives_the_float_hessian_layers():
    # octaves >= 2 read an int32 integral image when the sums fit; same det(H) as float64
    from frontend.features.surf import block_sums, integral_image

    img = block_sums(_texture(10, (240, 320)), 2)
    pad = 40
    padded = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    ii32 = integral_image(padded, 51)
    ii64 = cv2.integral(padded, sdepth=cv2.CV_64F)
    assert ii32.dtype == np.int32 and np.array_equal(ii32, ii64)
    for step, L in ((2, 39), (2, 51), (4, 51)):
        ny, nx = img.shape[0] // step, img.shape[1] // step
        a, sa = hessian_layer(ii32, pad, step, ny, nx, L, value_scale=1 / 1020)
        b, sb = hessian_layer(ii64, pad, step, ny, nx, L, value_scale=1 / 1020)
        assert a.dtype == b.dtype == np.float32
        assert np.abs(a - b).max() < 1e-5 * np.abs(b).max()
        assert np.array_equal(sa, sb)
    # sums that could overflow int32 stay float64
    assert integral_image(np.full((200, 200), 60000, np.uint16), 195).dtype == np.float64


def test_dense_layer_with_shared_padding_is_the_same():
    img = _block_sums_of(11)
    P = 9
    padded = (cv2.copyMakeBorder(img, P, P, P, P, cv2.BORDER_REPLICATE), P)
    for L in (9, 15, 27):
        a, sa = hessian_layer_dense(img, L, value_scale=1 / 1020)
        b, sb = hessian_layer_dense(img, L, value_scale=1 / 1020, padded=padded)
        assert np.array_equal(a, b) and np.array_equal(sa, sb)


def _block_sums_of(seed: int) -> np.ndarray:
    from frontend.features.surf import block_sums

    return block_sums(_texture(seed, (240, 320)), 2)
