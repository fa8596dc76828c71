"""The pictures a user judges a tracking by: the overlay shows where the fitted hand's wrist is (a
fit upside down, wrist among the fingertips, is seen), the segmentation's outline stays visible where
the fitted silhouette covers it, and a contact sheet's title is never cut off."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from handmodel import HandModel
from tracker.io.cameras import preset
from tracker.plots import OVERLAY_COLOURS, contact_sheet, contact_sheet_figure, model_silhouette, overlay_png, project

# the overlay's image area starts below a 60 px strip of title and key (see overlay_png)
TOP = 60


@pytest.fixture(scope="module")
def scene():
    """A hand 0.5 m in front of an SR305, its fingers pointing down the image, over a wall at 0.8 m."""
    hand = HandModel.load()
    cam = preset("sr305")
    theta = hand.zero()
    theta[2] = 0.5
    sil = model_silhouette(hand, theta, cam, (cam.height, cam.width))
    depth = np.full((cam.height, cam.width), 0.8)
    depth[sil] = 0.5
    depth[:40] = np.nan  # a band without depth
    return hand, cam, theta, sil, depth


def _rgb(path):
    return np.asarray(Image.open(path).convert("RGB"), float) / 255.0


def _near(img, colour, tol=0.12):
    return np.all(np.abs(img - np.asarray(colour)) < tol, axis=-1)


def test_the_wrist_is_marked_and_only_there(scene, tmp_path):
    """Old overlays drew every keypoint alike: a hand fitted upside down looked plausible."""
    hand, cam, theta, sil, depth = scene
    overlay_png(tmp_path / "o.png", depth, cam, hand, theta, "tracked", mask=sil)
    img = _rgb(tmp_path / "o.png")
    assert img.shape[:2] == (cam.height + TOP, cam.width)
    wrist_px = np.argwhere(_near(img, OVERLAY_COLOURS["wrist"]))
    assert len(wrist_px) >= 20
    u, v = project(hand.keypoints(theta), cam)
    names = hand.keypoint_names
    w = names.index("wrist")
    # every pixel of the wrist colour is the wrist's marker, around its projection
    dist = np.hypot(wrist_px[:, 1] - u[w], wrist_px[:, 0] - TOP - v[w])
    assert dist.max() < 8
    for tip in ("index_tip", "middle_tip", "pinky_tip"):
        t = names.index(tip)
        assert np.hypot(u[t] - u[w], v[t] - v[w]) > 40  # the test means something: tips far from the wrist


def test_the_mask_outline_shows_over_the_fit(scene, tmp_path):
    """The mask's outline is drawn over the fitted silhouette's fill: where the mask ends inside the
    fitted hand (a finger fitted where nothing was segmented) the user still sees it end."""
    hand, cam, theta, sil, depth = scene
    mask = sil.copy()
    mask[300:] = False  # the fingers' ends not segmented: the mask's lower edge crosses the fit
    overlay_png(tmp_path / "o.png", depth, cam, hand, theta, "tracked", mask=mask)
    img = _rgb(tmp_path / "o.png")
    cols = np.flatnonzero(sil[300] & sil[299])
    assert len(cols) > 20
    green = _near(img[TOP + 298:TOP + 302, cols], OVERLAY_COLOURS["mask"], tol=0.25).any(axis=0)
    assert green.mean() > 0.8, green.mean()
    # the fitted silhouette below the mask is red-tinted (but where a bone crosses), not the mask's colour
    below = img[TOP + 320, np.flatnonzero(sil[320])]
    assert len(below) > 20 and np.mean(below[:, 0] > below[:, 1] + 0.15) > 0.8


def test_no_fit_and_empty_mask_still_draw_the_depth(scene, tmp_path):
    hand, cam, theta, sil, depth = scene
    overlay_png(tmp_path / "o.png", depth, cam, hand, np.full(26, np.nan), "lost", mask=np.zeros_like(sil))
    img = _rgb(tmp_path / "o.png")[TOP:]
    assert not _near(img, OVERLAY_COLOURS["wrist"]).any() and not _near(img, OVERLAY_COLOURS["mask"], 0.25).any()
    # the nearer hand is lighter than the wall behind it; no depth is white
    assert img[int(project(hand.keypoints(theta), cam)[1][0]) + 20, 314].mean() > img[450, 50].mean() + 0.2
    assert np.allclose(img[10, 10], 1.0)


def test_contact_sheet_title_fits_one_panel(tmp_path):
    """A sheet of one or two frames was narrower than its title, which was cut off on both sides."""
    depths = [np.full((576, 640), 800.0)]
    title = "azure_kinect_recording.mkv: 1 frames, azure_kinect_nfov_unbinned 640×576; grey = no depth; " \
            "white = segmented"
    fig, _ = contact_sheet_figure(depths, ["#0  0.00 s"], title)
    fig.canvas.draw()
    box = fig._suptitle.get_window_extent()
    width, _ = fig.canvas.get_width_height()
    assert box.x0 >= 0 and box.x1 <= width, (box, width)
    lo, hi = contact_sheet(tmp_path / "s.png", depths, ["#0  0.00 s"], title)
    assert (tmp_path / "s.png").stat().st_size > 0 and hi > lo


def test_show_draws_the_fitted_skeletons_of_a_keypoints_csv(scene, tmp_path):
    """tracker show --keypoints: every shown frame's fit on one sheet (the wrist a blue square), so a
    run fitted upside down is seen at a glance; a frame without a fit has none; keypoints of another
    recording are refused."""
    import pandas as pd
    from typer.testing import CliRunner

    from tracker.cli import app
    from tracker.io.recording import RecordingWriter
    from tracker.io.tracking_file import keypoints_table

    hand, cam, theta, sil, depth = scene
    with RecordingWriter(tmp_path / "rec", cam, 30, "left") as w:
        for _ in range(3):
            w.write(depth)
    thetas = np.stack([theta, np.full(26, np.nan), theta])
    df = pd.DataFrame(thetas, columns=hand.dof_names)
    df.insert(0, "frame", [0, 1, 2])
    keypoints_table(hand, df).to_csv(tmp_path / "kp.csv", index=False)

    def run(*args):
        return CliRunner().invoke(app, ["show", str(tmp_path / "rec"), *map(str, args)])

    r = run("-o", tmp_path / "s.png", "--keypoints", tmp_path / "kp.csv")
    assert r.exit_code == 0, r.output
    assert "2 of 3 frames shown" in r.stdout
    img = _rgb(tmp_path / "s.png")
    assert _near(img, OVERLAY_COLOURS["wrist"]).sum() >= 6  # two small squares
    r = run("-o", tmp_path / "plain.png")
    assert r.exit_code == 0 and not _near(_rgb(tmp_path / "plain.png"), OVERLAY_COLOURS["wrist"]).any()
    kp = pd.read_csv(tmp_path / "kp.csv")
    kp.assign(frame=kp["frame"] + 5).to_csv(tmp_path / "other.csv", index=False)
    r = run("-o", tmp_path / "o.png", "--keypoints", tmp_path / "other.csv")
    assert r.exit_code == 2 and "other.csv: has frames up to 7, the recording 3" in r.stderr, r.output
    r = run("-o", tmp_path / "o.png", "--keypoints", tmp_path / "rec" / "recording.yaml")
    assert r.exit_code == 2 and "not a keypoints CSV of tracker track" in r.stderr, r.output
    assert not (tmp_path / "o.png").exists()
