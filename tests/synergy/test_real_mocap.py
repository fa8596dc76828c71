"""Marker IK on real third-party recordings (../shared/data): the DFKI glove and ART joint centres."""
import numpy as np
import pytest

from conftest import shared
from synergy.angles import markers_to_angles
from synergy.c3d import read_c3d


@pytest.fixture(scope="module")
def art():
    return read_c3d(shared("c3dorg_art_hands", "ART-Human_hands_real_no6dof.c3d"))


def test_dfki_glove_recording_converts():
    data = read_c3d(shared("dfki_hand_embodiment", "DERIVED_recording_tsv_to.c3d"))
    df = markers_to_angles(data, "dfki-glove13", hand="right")
    r = df["residual_mm"].to_numpy()
    print(f"\ndfki glove: residual median {np.nanmedian(r):.2f} mm, 95th {np.nanpercentile(r, 95):.2f} mm, "
          f"hand scale {df.attrs['calibration']['scale']:.3f}")
    assert len(df) == 6000 and (df["quality"] == "ok").mean() > 0.99
    assert np.nanmedian(r) <= 2.0 and np.nanpercentile(r, 95) <= 5.0
    # arm, back and pillow markers are known extras, silently ignored
    assert df.attrs["extra_markers"] == []
    # real occlusion gaps (thumb_tip 8.2 %) did not break the conversion
    assert df.attrs["gap_fraction"] > 0.005


@pytest.mark.slow
@pytest.mark.parametrize("hand", ["left", "right"])
def test_art_joint_centres_both_hands(art, hand):
    df = markers_to_angles(art, "art-joint-centres", hand=hand)
    r = df["residual_mm"].to_numpy()
    print(f"\nART {hand}: residual median {np.nanmedian(r):.2f} mm, 95th {np.nanpercentile(r, 95):.2f} mm")
    assert np.nanmedian(r) <= 3.0
    assert (df["quality"] == "ok").all()

    def flex(f):
        return df[[f"{f}1_flex", f"{f}2_flex", f"{f}3_flex"]].sum(axis=1).to_numpy()

    # ART measures thumb, index and middle and couples ring and pinky to the middle finger
    for f in ("ring", "pinky"):
        assert np.corrcoef(flex(f), flex("middle"))[0, 1] >= 0.9
    # fingers really move in this recording
    pip = np.degrees(-df["index2_flex"].to_numpy())
    assert np.nanmax(pip) - np.nanmin(pip) > 30
