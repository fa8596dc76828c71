"""Tracking on mesh-rendered synthetic depth with real (fingerfist) trajectories: accuracy per mode,
the occluded grasp, single-frame fits, bad input and recovery."""
from types import SimpleNamespace

import numpy as np
import pytest

from conftest import shared
from handmodel import HandModel
from tracker import experiments as E
from tracker.errors import TrackerError
from tracker.track import HandTracker, TrackerSettings

HAND = HandModel.load()
# Kinect v1 intrinsics (the tests do not depend on the camera-preset module)
CAM = SimpleNamespace(width=640, height=480, fx=575.8, fy=575.8, cx=319.5, cy=239.5, name="kinect1")


@pytest.fixture(scope="module")
def bundle():
    from synergy.bundle import load_bundle

    return load_bundle("fingerfist")


@pytest.fixture(scope="module")
def postures():
    shared("htrack_schroeder", "fingerfist.txt")
    return E.fingerfist_postures()


def _run(bundle, postures, mode, start, n=40, distance=0.75, **kw):
    truth = E.sequence(postures[start:start + n], bundle.model.mean_, distance=distance)
    tr = HandTracker(HAND, TrackerSettings(mode=mode, **kw), synergies=bundle)
    return E.run_sequence(HAND, truth, CAM, tr, lead=10), truth, tr


@pytest.mark.parametrize("start,distance", [(300, 0.6), (3000, 0.9)])
def test_full_dof_noise_free(bundle, postures, start, distance):
    r, _, _ = _run(bundle, postures, "full", start, distance=distance)
    print(f"\nfull DoF, rows {start}+, {distance} m: {r.mean_error:.2f} deg, {1000 / r.median_ms:.0f} fps")
    assert r.mean_error <= 2.0
    assert (r.status[1:] == "tracked").all()


def test_reduced_is_limited_only_by_its_subspace(bundle, postures):
    r, truth, tr = _run(bundle, postures, "reduced", 300)
    recon = float(np.mean(E.posture_error_deg(tr.reduced.project(truth), truth, HAND.pose_mask)[10:]))
    print(f"\nreduced ({tr.n_pcs} PCs, 99 %): {r.mean_error:.2f} deg; projection of the truth alone {recon:.2f} deg")
    # the result stays inside the subspace and the tracking adds little to the subspace's own error
    np.testing.assert_allclose(tr.reduced.project(r.theta[10:]), r.theta[10:], atol=1e-9)
    assert r.mean_error <= recon + 1.0
    assert r.mean_error <= 3.0


def test_hierarchical_tracking(bundle, postures):
    r, _, _ = _run(bundle, postures, "hierarchical", 300)
    assert r.mean_error <= 2.0


def test_occluded_grasp_reduced_beats_full():
    res = E.experiment_occlusion(HAND, CAM, frames=36)
    print(f"\noccluded grasp: full {res['full']:.2f} deg, reduced ({res['n_pcs']} PCs) {res['reduced']:.2f} deg")
    assert res["reduced"] <= res["full"] / 3


@pytest.mark.slow
def test_single_frame_hierarchical_better_than_flat(bundle, postures):
    """From the global pose only (posture unknown). The paper reports 22° flat vs 0.4° hierarchical;
    we reach ~4° median hierarchical (README), and hierarchical must beat flat."""
    res = E.experiment_single_frame(HAND, bundle, CAM, n=6, icp=20, seed=1)
    print(f"\nsingle frame: flat {res['flat']} hierarchical {res['hierarchical']} (mean, median deg)")
    assert res["hierarchical"][0] < res["flat"][0]
    assert res["hierarchical"][1] <= 6.0


def test_blank_frames_lost_then_recovered(bundle, postures):
    truth = E.sequence(postures[3000:3040], bundle.model.mean_)
    tr = HandTracker(HAND, TrackerSettings(mode="full"), synergies=bundle)
    r = E.run_sequence(HAND, truth, CAM, tr, lead=10, blank=(20, 30))
    assert (r.status[20:30] == "lost").all()
    back = r.error_deg[33:]
    print(f"\nafter 10 blank frames: status {list(r.status[30:34])}, error {np.round(r.error_deg[30:36], 2)}")
    assert np.nanmean(back) <= 2.0


@pytest.mark.parametrize("bad", [np.zeros((0, 3)), np.full((100, 3), np.nan), np.zeros((5, 3))])
def test_bad_points_give_lost_not_crash(bad):
    tr = HandTracker(HAND, TrackerSettings(mode="full"))
    r = tr.step(bad)
    assert r.status == "lost"


def test_bad_settings():
    with pytest.raises(TrackerError, match="mode must be one of"):
        HandTracker(HAND, TrackerSettings(mode="fast"))
    with pytest.raises(TrackerError, match="needs a synergy bundle"):
        HandTracker(HAND, TrackerSettings(mode="reduced"))
