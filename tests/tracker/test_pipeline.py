"""The tracker's named stages: the paper's settings, ICP schedules, one fit alone, the run stage and the
tracking-output file."""
import io

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings as hsettings, strategies as st

from handmodel import HandModel
from handmodel.dofs import DOF_NAMES
from handmodel.subspace import Subspace
from tracker.correspond import CorrespondSettings, Matcher
from tracker.errors import TrackerError
from tracker.icp import IcpSettings, Stage, fit, search_schedule, tracking_schedule
from tracker.init import InitSettings
from tracker.io.tracking_file import (FRAME_COLUMNS, keypoints_table, parse_tracking, read_tracking, tracking_csv,
                                       write_tracking)
from tracker.observe import ObserveSettings
from tracker.run import track_recording
from tracker.track import FrameTracker, TrackerSettings

HAND = HandModel.load()


@pytest.fixture(scope="module")
def bundle():
    from synergy.bundle import load_bundle

    return load_bundle("fingerfist")


def test_paper_settings_are_the_papers_method():
    """§VI and FORMAT.md §5: 1 rigid + 4 non-rigid ICP iterations × 5 Gauss-Newton steps, every 3rd
    pixel in x and y, pairs ≥ 50 mm rejected, λ = 1 on posture and 0 on pose, plain least squares on
    data→model pairs; none of what we add (silhouette term, Cauchy weights, normal test, smoothing,
    adaptive stride, start search, finger search, projected steps)."""
    p = TrackerSettings.paper()
    assert (p.icp.rigid_iterations, p.icp.icp_iterations, p.icp.gn_iterations) == (1, 4, 5)
    assert (p.icp.damping, p.icp.pose_damping) == (1.0, 0.0)
    assert p.observe.stride == 3 and p.observe.target_points is None and p.observe.smooth == 0
    assert p.correspond.reject_mm == 50.0 and p.correspond.model == "capsules"
    assert p.correspond.normal_agreement <= -1
    assert p.icp.silhouette_weight == 0 and p.icp.robust_mm == 0 and not p.icp.point_to_plane
    assert p.icp.projected_steps == 0
    assert not p.init.finger_search and not p.init.search
    # and our defaults do differ from it in exactly what we add
    d = TrackerSettings()
    assert d.icp.silhouette_weight > 0 and d.icp.robust_mm > 0 and d.init.finger_search and d.init.search
    assert (d.icp.rigid_iterations, d.icp.icp_iterations, d.icp.gn_iterations) == (1, 4, 5)
    # a change to the paper's method changes only what it names
    r = TrackerSettings.paper(mode="reduced", observe=dict(stride=4))
    assert r.mode == "reduced" and r.observe.stride == 4 and r.icp.robust_mm == 0 and p.observe.stride == 3


def test_replace_changes_groups_by_dict_and_refuses_unknown_names():
    s = TrackerSettings().replace(icp=dict(robust_mm=2.0), observe=dict(smooth=0), correspond=dict(model="mesh"), init=dict(icp_iterations=7), mode="reduced")
    assert (s.icp.robust_mm, s.observe.smooth, s.correspond.model, s.init.icp_iterations, s.mode) == (2.0, 0, "mesh", 7, "reduced")
    assert TrackerSettings().icp.robust_mm == 8.0  # the default is untouched
    with pytest.raises(TrackerError, match="IcpSettings has no field 'robust'"):
        TrackerSettings().replace(icp=dict(robust=2.0))
    with pytest.raises(TrackerError, match="TrackerSettings has no field 'robust_mm'"):
        TrackerSettings().replace(robust_mm=2.0)  # the flat names of before are gone: one name per field
    s = TrackerSettings().replace(icp=IcpSettings(icp_iterations=9))
    assert s.icp.icp_iterations == 9 and s.icp.robust_mm == 8.0


@given(st.sampled_from(["full", "reduced", "hierarchical"]), st.integers(0, 10), st.integers(0, 4), st.integers(0, 3))
@hsettings(max_examples=60, deadline=None)
def test_tracking_schedule(mode, n, projected, coarse):
    full = Subspace.full(HAND, HAND.limits)
    red = Subspace.full(HAND, HAND.limits)  # any other object stands for the synergy subspace
    s = tracking_schedule(mode, n, full, red, projected_steps=projected, coarse_iterations=coarse)
    assert len(s) == n
    if mode == "full":
        assert all(x.subspace is full and x.entry == "none" and x.project is None for x in s)
    elif mode == "reduced":
        proj = [x.project is red for x in s]
        # the last `projected` iterations, never the first
        assert sum(proj) == (min(projected, max(n - 1, 0)) if projected else 0)
        assert proj == sorted(proj) and (n == 0 or not proj[0])
        assert all((x.subspace is full) == (x.project is red) for x in s)
        assert all(x.entry == "clamp" for x in s if x.project is None)
    else:
        assert [x.entry for x in s] == ["through"] * min(coarse, n) + ["none"] * max(n - coarse, 0)


def test_search_schedule_spreads_the_ladder_coarse_to_fine():
    full = Subspace.full(HAND, HAND.limits)
    a, b = object(), object()
    s = search_schedule("hierarchical", 6, full, None, [a, b, full])
    assert [x.subspace for x in s] == [a, a, b, b, full, full]
    assert [x.entry for x in s] == ["clamp"] * 4 + ["none"] * 2
    assert {x.entry for x in search_schedule("hierarchical", 3, full, None, [a, full], through=True)} == {"through", "none"}
    with pytest.raises(TrackerError, match="needs a synergy subspace"):
        tracking_schedule("reduced", 3, full, None)


@pytest.mark.parametrize("seed", range(5))
def test_one_icp_fit_alone(seed):
    """The icp stage on its own, on points sampled on the capsule surface facing a camera at the
    origin: the truth is a fixed point of the fit, and from a start 3 mm and 2° per joint off the fit
    error at least halves and the hand's position comes back to within 2.5 mm."""
    from handmodel.geometry import surface_samples

    rng = np.random.default_rng(seed)
    theta = np.zeros(26)
    theta[2], theta[3] = 0.7, -0.3
    theta[6:] = rng.uniform(HAND.limits[6:, 0], HAND.limits[6:, 1]) * 0.4
    P, _, N = surface_samples(HAND, theta, spacing=0.003)
    pts = P[np.einsum("ij,ij->i", P, N) < 0]
    full = Subspace.full(HAND, HAND.limits)
    m = Matcher(HAND, CorrespondSettings(normal_agreement=-1))
    st_ = IcpSettings(silhouette_weight=0)
    th, corr = fit(HAND, pts, theta, [Stage(full)] * 3, m, st_, n_rigid=1)
    np.testing.assert_allclose(th, theta, atol=1e-5)
    assert corr.fit_error_mm() < 1e-3
    start = theta.copy()
    start[:3] += rng.normal(0, 0.003, 3)
    start[6:] += np.radians(2.0) * rng.choice([-1, 1], 20)
    before = m(start, pts).fit_error_mm()
    th, corr = fit(HAND, pts, start, [Stage(full)] * 10, m, st_, n_rigid=1)
    assert corr.fit_error_mm() < before / 2
    assert np.abs(th[:3] - theta[:3]).max() < 0.0025


class _MemoryRecording:
    """A recording in memory (what track_recording needs): camera and frames."""

    def __init__(self, camera, depths):
        from types import SimpleNamespace

        self.camera = camera
        self.frames = [SimpleNamespace(index=i, time_s=i / 30.0, depth=d, color=None) for i, d in enumerate(depths)]

    def __iter__(self):
        return iter(self.frames)


def test_track_recording_then_write_and_read_back(bundle, tmp_path):
    """The run stage over rendered frames (one unusable: wrong size), the output written, read back
    identical, the keypoints table, and bad outputs refused."""
    from tracker.io.cameras import preset
    from tracker.sim import experiments as E
    from tracker.sim.render import DepthRenderer

    cam = preset("kinect1")
    truth = E.sequence(np.tile(bundle.model.mean_, (6, 1)), bundle.model.mean_, lead=0, distance=0.7)
    ren = DepthRenderer(HAND, cam)
    depths = [ren.render(t, labels=False).depth for t in truth]
    depths[3] = np.zeros((10, 10))  # not this camera's size: tracked as empty, so lost
    tr = FrameTracker(HAND, TrackerSettings().replace(scale=dict(hand_scale=1.0)), synergies=bundle)
    seen = []
    df = track_recording(_MemoryRecording(cam, depths), tr, lambda f, r, ob: seen.append((f.index, ob is None)))
    assert list(df.columns) == [*FRAME_COLUMNS, *DOF_NAMES] and len(df) == 6
    assert seen == [(0, False), (1, False), (2, False), (3, True), (4, False), (5, False)]
    assert df["status"].tolist()[:4] == ["reinit", "tracked", "tracked", "lost"] and df["points"][3] == 0
    err = E.posture_error_deg(df[list(DOF_NAMES)].to_numpy()[[0, 1, 2, 4, 5]], truth[[0, 1, 2, 4, 5]], HAND.pose_mask)
    assert np.max(err) < 2.0
    out = write_tracking(tmp_path / "t.csv", df, {"mode": "full", "units": "metres, radians"})
    back, meta = read_tracking(out)
    assert meta == {"mode": "full", "units": "metres, radians"}
    pd.testing.assert_frame_equal(back, df, check_exact=False, rtol=1e-8)
    with pytest.raises(Exception, match="exists"):
        write_tracking(out, df, {})
    kp = keypoints_table(HAND, df)
    assert kp.shape == (6, 1 + 63)
    np.testing.assert_allclose(kp.iloc[0, 1:].to_numpy(float).reshape(21, 3),
                               HAND.keypoints(df[list(DOF_NAMES)].to_numpy()[0]) * 1000.0, atol=1e-6)
    with pytest.raises(TrackerError, match="missing columns fit_mm"):
        parse_tracking(io.StringIO(tracking_csv(df.drop(columns="fit_mm"), {})), "x.csv")
    with pytest.raises(TrackerError, match="unknown status"):
        parse_tracking(io.StringIO(tracking_csv(df.assign(status="ok"), {})), "x.csv")


def test_stage_settings_are_checked():
    with pytest.raises(TrackerError, match="model must be one of"):
        FrameTracker(HAND, TrackerSettings().replace(correspond=dict(model="spheres")))
    with pytest.raises(TrackerError, match="subspace.limits: must be one of"):
        FrameTracker(HAND, TrackerSettings().replace(subspace=dict(limits="none")))
    with pytest.raises(TrackerError, match="must not be negative"):
        FrameTracker(HAND, TrackerSettings().replace(icp=dict(robust_mm=-1.0)))
    assert isinstance(TrackerSettings().observe, ObserveSettings) and isinstance(TrackerSettings().init, InitSettings)
