"""Camera projection and point clouds: round trips, a plane at known depth, stride sampling, crops."""
import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from tracker.cameras import Camera, preset
from tracker.pointcloud import (backproject, crop, crop_depth, depth_range, in_box, kept_fraction, stride_for_density,
                                stride_mask)

cameras = st.builds(
    lambda w, h, fx, fy, cxr, cyr: Camera(w, h, fx, fy, cxr * (w - 1), cyr * (h - 1)),
    st.integers(1, 700), st.integers(1, 500), st.floats(50.0, 2000.0), st.floats(50.0, 2000.0),
    st.floats(0.0, 1.0), st.floats(0.0, 1.0))


@given(cameras, st.data())
@settings(max_examples=200, deadline=None)
def test_unproject_then_project_returns_the_pixel(cam, data):
    u = data.draw(st.floats(-0.5, cam.width - 0.5))
    v = data.draw(st.floats(-0.5, cam.height - 0.5))
    z = data.draw(st.floats(0.05, 20.0))
    p = cam.unproject([u, v], z)
    assert p[2] == z
    np.testing.assert_allclose(cam.project(p), [u, v], rtol=0, atol=1e-9 * max(cam.width, cam.height))


@given(cameras, st.integers(0, 2**32 - 1))
@settings(max_examples=50, deadline=None)
def test_backproject_image_then_project_returns_pixel_grid(cam, seed):
    if cam.width * cam.height > 20_000:
        cam = cam.with_size(100, 80)
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.2, 5.0, cam.shape)
    depth[rng.random(cam.shape) < 0.3] = np.nan
    pts, pix = backproject(depth, cam)
    np.testing.assert_array_equal(pix, np.argwhere(np.isfinite(depth)))
    uv = cam.project(pts)
    np.testing.assert_allclose(uv[:, 0], pix[:, 1], atol=1e-8)
    np.testing.assert_allclose(uv[:, 1], pix[:, 0], atol=1e-8)
    np.testing.assert_array_equal(pts[:, 2], depth[pix[:, 0], pix[:, 1]])
    # the image-shaped variant agrees
    X = cam.backproject(depth)
    np.testing.assert_allclose(X[pix[:, 0], pix[:, 1]], pts, rtol=1e-12)
    assert np.isnan(X[~np.isfinite(depth)]).all()


def test_plane_at_known_depth():
    cam = preset("kinect1")
    z0 = 0.8
    pts, pix = backproject(np.full(cam.shape, z0), cam)
    assert len(pts) == cam.width * cam.height
    np.testing.assert_allclose(pts[:, 2], z0)
    # x right, y down: the top-left pixel is left of and above the optical axis
    assert pts[0, 0] < 0 and pts[0, 1] < 0 and tuple(pix[0]) == (0, 0)
    lo, hi = pts.min(0), pts.max(0)
    assert lo[0] == pytest.approx(-cam.cx * z0 / cam.fx)
    assert hi[0] == pytest.approx((cam.width - 1 - cam.cx) * z0 / cam.fx)
    assert lo[1] == pytest.approx(-cam.cy * z0 / cam.fy)
    assert hi[1] == pytest.approx((cam.height - 1 - cam.cy) * z0 / cam.fy)
    # Kinect v1: about 0.88 m × 0.66 m of plane at 0.8 m (a 57.5° × 44.8° field of view)
    assert hi[0] - lo[0] == pytest.approx(0.877, abs=0.002) and hi[1] - lo[1] == pytest.approx(0.658, abs=0.002)


def test_backproject_float32_and_mask():
    cam = Camera(8, 6, 10.0, 10.0, 3.5, 2.5)
    depth = np.full(cam.shape, 1.0, np.float32)
    depth[0, 0] = 0.0  # no data
    mask = np.zeros(cam.shape, bool)
    mask[:, :4] = True
    pts, pix = backproject(depth, cam, mask=mask, dtype=np.float32)
    assert pts.dtype == np.float32 and len(pts) == 6 * 4 - 1 and pix[:, 1].max() == 3
    assert cam.backproject(depth).dtype == np.float32
    with pytest.raises(ValueError, match="does not match"):
        backproject(np.ones((5, 5)), cam)
    with pytest.raises(ValueError, match="stride"):
        backproject(depth, cam, stride=0)


@pytest.mark.parametrize("H, W, K", [(480, 640, 1), (480, 640, 3), (424, 512, 5), (7, 11, 2), (5, 5, 7)])
def test_stride_keeps_ceil_h_over_k_times_ceil_w_over_k(H, W, K):
    cam = Camera(W, H, 500.0, 500.0, (W - 1) / 2, (H - 1) / 2)
    pts, pix = backproject(np.full((H, W), 0.7), cam, stride=K)
    assert len(pts) == math.ceil(H / K) * math.ceil(W / K) == stride_mask((H, W), K).sum()
    assert np.all(pix % K == 0)
    assert kept_fraction((H, W), K) == len(pts) / (H * W)
    if H % K == 0 and W % K == 0:
        assert kept_fraction((H, W), K) == pytest.approx(1 / K**2)


def test_stride_for_density():
    assert stride_for_density(1.0) == 1
    assert stride_for_density(1 / 9) == 3  # the original "1/3 sampling"
    assert stride_for_density(0.1) == 3 and stride_for_density(0.12) == 2 and stride_for_density(1 / 16) == 4
    for f in np.linspace(0.001, 1, 97):
        k = stride_for_density(f)
        assert 1 / k**2 >= f * (1 - 1e-12) and (k == 1 or 1 / (k + 1) ** 2 < f)
    with pytest.raises(ValueError):
        stride_for_density(0)


def test_crops():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-1, 1, (1000, 3))
    pix = np.arange(1000)
    inside, ip = crop(pts, (-0.5, -0.5, 0.0), (0.5, 0.5, 0.5), pix)
    m = np.all((pts >= [-0.5, -0.5, 0.0]) & (pts <= 0.5), axis=1)
    np.testing.assert_array_equal(inside, pts[m])
    np.testing.assert_array_equal(ip, pix[m])
    np.testing.assert_array_equal(crop_depth(pts, 0.2, 0.4), pts[(pts[:, 2] >= 0.2) & (pts[:, 2] <= 0.4)])
    np.testing.assert_array_equal(in_box(pts, (None, None, 0.9), (None, None, None)), pts[:, 2] >= 0.9)
    d = np.array([[0.3, np.nan], [0.9, 1.6]])
    np.testing.assert_array_equal(depth_range(d, 0.5, 1.5), [[np.nan, np.nan], [0.9, np.nan]])
    assert d[0, 0] == 0.3 and d[1, 1] == 1.6  # input untouched


def test_observe_stride_matches_pointcloud_stride():
    """The tracker's observation sampling uses the same grid (every K-th pixel from (0, 0))."""
    from tracker.observe import observe

    cam = preset("kinect1")
    d = np.full(cam.shape, np.nan)
    d[100:200, 300:400] = 0.7
    ob = observe(d, cam, stride=3)
    pts, _ = backproject(d, cam, stride=3)
    assert len(ob.points) == len(pts) == len(range(102, 200, 3)) * len(range(300, 400, 3))
    np.testing.assert_allclose(np.sort(ob.points, axis=0), np.sort(pts, axis=0))
