"""Sensor noise: measured statistics against the documented σ(z), quantisation, shadows, dropout."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from tracker.errors import TrackerError
from tracker.sim.noise import PRESETS, NoiseModel

CAM = SimpleNamespace(width=640, height=480, fx=580.0, fy=580.0, cx=319.5, cy=239.5)


def nguyen_sigma(z):
    """Nguyen, Izadi & Lovell 2012, axial noise for 10°–60° incidence (metres)."""
    return 0.0012 + 0.0019 * (z - 0.4) ** 2


def rendered_wall(hand, z):
    """A fronto-parallel plane at depth z through the renderer (hand behind the camera), with incidence."""
    from tracker.sim.render import Clutter, render

    th = np.zeros(26)
    th[2] = -1.0
    wall = Clutter(forearm=False, table=True, table_point=(0.0, 0.0, z), table_normal=(0.0, 0.0, -1.0))
    r = render(hand, th, CAM, clutter=wall, incidence=True)
    return r.depth, r.cos_incidence


@pytest.mark.parametrize("z", [0.6, 1.0, 1.5])  # inside the preset's 0.5-5 m range, so nothing is clipped
def test_kinect1_axial_noise_matches_documented_sigma(hand, z):
    depth, cosi = rendered_wall(hand, z)
    assert np.allclose(depth, z, atol=1e-6)
    k1 = NoiseModel.preset("kinect1")
    noisy = k1.apply(depth, CAM, np.random.default_rng(11), cosi)
    ok = np.isfinite(noisy)
    assert ok.mean() > 0.99  # a wall has no silhouette, no shadow
    err = noisy[ok] - depth[ok]
    assert abs(np.std(err) / nguyen_sigma(z) - 1) < 0.10, (z, np.std(err), nguyen_sigma(z))
    assert abs(np.mean(err)) < 0.2 * nguyen_sigma(z)
    # the documented curve itself is Nguyen's (angle term negligible on this wall)
    assert np.allclose(k1.sigma_z(z), nguyen_sigma(z))
    assert np.all(k1.sigma_z(z, cosi) - nguyen_sigma(z) < 0.05 * nguyen_sigma(z))


@pytest.mark.parametrize("z", [0.5, 1.0, 1.5])
def test_gaussian_axial_part_alone(z):
    m = NoiseModel(axial=True)
    d = np.full((300, 300), z, np.float32)
    err = m.apply(d, CAM, np.random.default_rng(5)).astype(float) - z
    assert abs(np.std(err) / nguyen_sigma(z) - 1) < 0.05
    assert abs(np.mean(err)) < 3 * nguyen_sigma(z) / 300


def test_angle_term_grows_at_grazing_incidence():
    m = NoiseModel(axial=True, angle_terms=True)
    z = 1.0
    assert m.sigma_z(z, np.cos(np.radians(70))) > m.sigma_z(z, 1.0) + 0.0005
    th = np.radians(70)
    assert np.isclose(m.sigma_z(z, np.cos(th)), nguyen_sigma(z) + 0.0001 * th ** 2 / (np.pi / 2 - th) ** 2)


@pytest.mark.parametrize("z", [0.7, 1.0, 1.5])
def test_disparity_quantisation_steps(z):
    m = NoiseModel(quantize=True, focal_px=580.0)
    zs = np.linspace(z - 0.02, z + 0.02, 4001, dtype=np.float32).reshape(1, -1)
    q = m.apply(zs, CAM).astype(float).ravel()
    levels = np.unique(q)
    steps = np.diff(levels)
    expected = z ** 2 * 0.125 / (580.0 * 0.075)  # Δz = z²·Δd/(f·b)
    assert np.isclose(np.median(steps), expected, rtol=0.03), (np.median(steps), expected)
    assert np.allclose(m.quantization_step(z), expected)
    assert np.abs(q - zs.ravel()).max() <= 0.51 * steps.max()
    # every level is f·b / (k/8) for an integer k
    k = 580.0 * 0.075 / levels / 0.125
    assert np.allclose(k, np.round(k), atol=1e-3)


def test_projector_shadow_band_left_of_objects():
    d = np.full((120, 200), 1.0, np.float32)
    d[40:80, 100:140] = 0.6
    m = NoiseModel(shadow=True, focal_px=580.0)
    out = m.apply(d, CAM)
    lost = np.isnan(out)
    width = 580.0 * 0.075 * (1 / 0.6 - 1 / 1.0)  # ≈ 29 px
    row = lost[60]
    assert not row[100:].any()  # nothing lost on the object or to its right
    assert abs(row[:100].sum() - width) <= 1.5
    assert row[100 - int(width) + 1:100].all()
    assert not lost[:40].any() and not lost[80:].any()
    # projector on the other side: the band moves to the right
    right = np.isnan(NoiseModel(shadow=True, focal_px=580.0, projector_side=-1).apply(d, CAM))[60]
    assert not right[:140].any() and abs(right[140:].sum() - width) <= 1.5


def test_edge_dropout_band_and_probability():
    d = np.full((200, 200), np.nan, np.float32)
    d[50:150, 50:150] = 0.8
    all_drop = NoiseModel(edge_drop_prob=1.0, edge_width_px=2).apply(d, CAM)
    assert np.isnan(all_drop[50:52, 50:150]).all() and np.isnan(all_drop[50:150, 148:150]).all()
    assert np.isfinite(all_drop[52:148, 52:148]).all()
    half = NoiseModel(edge_drop_prob=0.5, edge_width_px=3).apply(d, CAM, np.random.default_rng(0))
    band = np.isfinite(d).copy()
    band[53:147, 53:147] = False
    assert abs(np.isnan(half[band]).mean() - 0.5) < 0.05
    assert np.isfinite(half[53:147, 53:147]).all()
    # a depth jump counts as an edge too
    step = np.full((100, 100), 1.0, np.float32)
    step[:, 50:] = 0.8
    out = NoiseModel(edge_drop_prob=1.0, edge_width_px=1).apply(step, CAM)
    assert np.isnan(out[:, 49:51]).all() and np.isfinite(out[:, :49]).all() and np.isfinite(out[:, 51:]).all()


def test_lateral_noise_frays_silhouettes_only():
    d = np.full((200, 200), np.nan, np.float32)
    d[50:150, 50:150] = 0.8
    out = NoiseModel(lateral_px=0.8).apply(d, CAM, np.random.default_rng(2))
    assert np.allclose(out[55:145, 55:145], 0.8)  # a flat face keeps its depth
    changed = np.isfinite(out) != np.isfinite(d)
    assert changed.sum() > 50 and not changed[:44].any() and not changed[56:144, 56:144].any()


def test_range_and_random_dropout():
    d = np.tile(np.linspace(0.3, 6.0, 100, dtype=np.float32), (50, 1))
    out = NoiseModel(range_m=(0.5, 5.0)).apply(d, CAM)
    assert np.array_equal(np.isfinite(out), (d >= 0.5) & (d <= 5.0))
    rnd = NoiseModel(random_drop_prob=0.1).apply(np.full((300, 300), 1.0, np.float32), CAM, np.random.default_rng(0))
    assert abs(np.isnan(rnd).mean() - 0.1) < 0.01


def test_deterministic_given_seed_and_noise_free_preset():
    d = np.full((60, 80), np.nan, np.float32)
    d[10:50, 20:60] = 0.75
    k1 = NoiseModel.preset("kinect1")
    a = k1.apply(d, CAM, np.random.default_rng(7))
    b = k1.apply(d, CAM, np.random.default_rng(7))
    c = k1.apply(d, CAM, np.random.default_rng(8))
    assert np.array_equal(a, b, equal_nan=True) and not np.array_equal(a, c, equal_nan=True)
    none = NoiseModel.preset("none")
    assert none.is_noise_free and not k1.is_noise_free
    assert np.array_equal(none.apply(d, CAM), d, equal_nan=True)


def test_presets_and_errors():
    assert {"none", "kinect1"} <= set(PRESETS)
    k1 = PRESETS["kinect1"]
    assert k1.axial and k1.quantize and k1.shadow and k1.edge_drop_prob > 0 and k1.range_m == (0.5, 5.0)
    assert not k1.with_(shadow=False).shadow
    with pytest.raises(TrackerError, match="kinect1"):
        NoiseModel.preset("kinect9")
    with pytest.raises(TrackerError):
        k1.with_(colour=True)
    with pytest.raises(TrackerError):
        NoiseModel(edge_drop_prob=1.5)
    with pytest.raises(TrackerError):
        NoiseModel(quantize=True).apply(np.ones((4, 4)))  # no focal length and no camera


# ----------------------------------------------------------------------------- RealSense
def intel_rms(z, subpixel=0.08, focal=1005.0, baseline=0.055):
    """Intel's D400 depth RMS error z²·subpixel/(f·B) (metres)."""
    return z ** 2 * subpixel / (focal * baseline)


@pytest.mark.parametrize("z", [0.6, 1.0, 1.5])
def test_d4xx_axial_noise_follows_intels_rms_formula(hand, z):
    depth, cosi = rendered_wall(hand, z)
    d4 = NoiseModel.preset("d4xx")
    assert np.isclose(d4.sigma_z(z), intel_rms(z))
    noisy = d4.with_(depth_step_m=0.0).apply(depth, CAM, np.random.default_rng(3), cosi)
    ok = np.isfinite(noisy)
    assert ok.mean() > 0.99  # a wall facing the camera: no edges, no grazing holes
    err = noisy[ok] - depth[ok]
    assert abs(np.std(err) / intel_rms(z) - 1) < 0.08, (z, np.std(err), intel_rms(z))
    # σ_z ∝ z²: the law of any triangulating sensor, not Kinect's offset curve
    assert np.isclose(d4.sigma_z(2 * z) / d4.sigma_z(z), 4.0)


def test_sr305_depth_steps_of_an_eighth_millimetre_and_its_range():
    sr = NoiseModel.preset("realsense")
    assert sr.name == "sr305" and sr.depth_step_m == 0.000125 and sr.range_m == (0.2, 1.5)
    d = np.tile(np.linspace(0.1, 2.0, 400, dtype=np.float64), (40, 1))
    out = sr.with_(shadow=False, lateral_px=0.0, edge_drop_prob=0.0, flying_prob=0.0).apply(
        d, CAM, np.random.default_rng(1)).astype(float)
    ok = np.isfinite(out)
    assert ok[:, (d[0] > 0.21) & (d[0] < 1.49)].mean() > 0.99
    assert not ok[:, (d[0] < 0.19) | (d[0] > 1.52)].any()  # (the range applies to the noisy depth)
    assert out[ok].min() >= 0.2 and out[ok].max() <= 1.5
    units = out[ok] / 0.000125
    assert np.abs(units - np.round(units)).max() < 0.02  # float32 storage of multiples of 0.125 mm


def test_flying_pixels_only_across_depth_jumps():
    step = np.full((100, 100), 1.0, np.float32)
    step[:, 50:] = 0.8
    all_fly = NoiseModel(flying_prob=1.0, edge_jump_m=0.02).apply(step, CAM, np.random.default_rng(0))
    mid = all_fly[:, 49:51]
    assert ((mid > 0.8 + 0.1 * 0.2 - 1e-6) & (mid < 1.0 - 0.1 * 0.2 + 1e-6)).all()  # between the two surfaces
    assert np.array_equal(all_fly[:, :49], step[:, :49]) and np.array_equal(all_fly[:, 51:], step[:, 51:])
    some = NoiseModel(flying_prob=0.3).apply(np.tile(step, (10, 1)), CAM, np.random.default_rng(1))
    moved = some[:, 49:51] != np.tile(step, (10, 1))[:, 49:51]
    assert abs(moved.mean() - 0.3) < 0.04
    # a silhouette against no data has nothing to mix with
    blob = np.full((60, 60), np.nan, np.float32)
    blob[20:40, 20:40] = 0.7
    assert np.array_equal(NoiseModel(flying_prob=1.0).apply(blob, CAM), blob, equal_nan=True)


def test_holes_on_grazing_and_dark_surfaces():
    theta = np.radians(np.linspace(0.0, 89.0, 90))
    cosi = np.tile(np.cos(theta), (2000, 1))
    d = np.full(cosi.shape, 0.7, np.float32)
    m = NoiseModel(grazing_deg=(60.0, 80.0))
    assert m.needs_incidence and not m.is_noise_free
    lost = np.isnan(m.apply(d, CAM, np.random.default_rng(0), cosi)).mean(0)
    expected = np.clip((np.degrees(theta) - 60.0) / 20.0, 0.0, 1.0)
    assert np.abs(lost - expected).max() < 0.05
    assert np.allclose(m.grazing_loss(cosi[0]), expected)
    # without the incidence image the part cannot apply
    assert np.isfinite(m.apply(d, CAM, np.random.default_rng(0))).all()
    refl = np.full(d.shape, 0.5)
    refl[:, :45] = 0.05
    dark = NoiseModel(dark_reflectance=0.15, dark_drop_prob=0.8)
    assert dark.needs_reflectance
    out = dark.apply(d, CAM, np.random.default_rng(2), reflectance=refl)
    assert abs(np.isnan(out[:, :45]).mean() - 0.8) < 0.01 and np.isfinite(out[:, 45:]).all()


def test_stereo_occlusion_band_of_the_d4xx():
    d = np.full((120, 200), 1.0, np.float32)
    d[40:80, 100:140] = 0.6
    d4 = NoiseModel.preset("d4xx").with_(axial=False, lateral_px=0.0, edge_drop_prob=0.0, flying_prob=0.0,
                                         depth_step_m=0.0, grazing_deg=None, dark_drop_prob=0.0)
    row = np.isnan(d4.apply(d, CAM))[60]
    width = CAM.fx * 0.055 * (1 / 0.6 - 1 / 1.0)  # ≈ 21 px at f = 580
    assert not row[100:].any() and abs(row[:100].sum() - width) <= 1.5


def test_realsense_presets_are_listed_and_validated():
    assert {"sr305", "d4xx"} <= set(PRESETS) and NoiseModel.preset("realsense") is PRESETS["sr305"]
    for name in ("sr305", "d4xx"):
        p = PRESETS[name]
        assert p.axial and p.axial_coeffs[0] == 0.0 and p.axial_coeffs[2] == 0.0  # σ_z ∝ z²
        assert p.needs_incidence and p.needs_reflectance and p.flying_prob > 0 and p.shadow
    assert not PRESETS["kinect1"].needs_reflectance
    with pytest.raises(TrackerError):
        NoiseModel(grazing_deg=(80.0, 60.0))
    with pytest.raises(TrackerError):
        NoiseModel(flying_prob=2.0)
    with pytest.raises(TrackerError):
        NoiseModel(depth_step_m=-1.0)
    with pytest.raises(TrackerError):
        NoiseModel.triangulation_coeffs(0.08, 0.0, 0.055)
