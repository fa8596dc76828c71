"""Many recordings at once: ``tracker track REC… -o OUTDIR`` one by one or with ``--dask local:2``
writes the same per-recording outputs as tracking each alone, a summary table, and reports a
failing recording while the others go on."""
from __future__ import annotations

import pandas as pd
import pytest
from typer.testing import CliRunner

from tracker.batch import SUMMARY_COLUMNS
from tracker.cli import app
from tracker.io.tracking_file import read_tracking

pytest.importorskip("distributed")


def _run(args):
    return CliRunner().invoke(app, [str(a) for a in args], env={"SYNERGY_PATH": ""})


@pytest.fixture(scope="module")
def recs(tmp_path_factory):
    d = tmp_path_factory.mktemp("batch")
    for name, motion in (("a", "grasp-back"), ("b", "spread")):
        r = _run(["synth", "--frames", "3", "--motion", motion, "--noise", "none", "-o", d / name])
        assert r.exit_code == 0, r.output
    (d / "broken").mkdir()  # not a recording: no recording.yaml
    for name in ("a", "b"):  # each alone: the reference
        r = _run(["track", d / name, "-o", d / f"{name}-alone.csv", "--no-check-hand"])
        assert r.exit_code == 0, r.output
    return d


def _same_tracking(got, want):
    """Equal frames, statuses, fit errors and θ, and the same header; the timing column differs by run."""
    (g, gm), (w, wm) = read_tracking(got), read_tracking(want)
    pd.testing.assert_frame_equal(g.drop(columns="ms"), w.drop(columns="ms"))
    assert gm == wm


@pytest.mark.parametrize("dask", [None, pytest.param("local:2", marks=pytest.mark.slow)])
def test_many_recordings_as_one_by_one(recs, tmp_path, dask):
    out = tmp_path / "out"
    r = _run(["track", recs / "a", recs / "broken", recs / "b", "-o", out, "--no-check-hand",
              *(["--dask", dask] if dask else [])])
    # the broken recording is reported, last, one line naming it; the others were tracked
    assert r.exit_code == 2, r.output
    assert r.stderr == f"error: {recs / 'broken' / 'recording.yaml'}: missing (not a recording folder)\n"
    for name in ("a", "b"):
        _same_tracking(out / f"{name}.csv", recs / f"{name}-alone.csv")
    summary = pd.read_csv(out / "summary.csv", keep_default_na=False)
    assert list(summary.columns) == list(SUMMARY_COLUMNS)
    assert summary["recording"].tolist() == [str(recs / n) for n in ("a", "broken", "b")]
    assert summary["error"].tolist()[0] == summary["error"].tolist()[2] == ""
    assert "missing (not a recording folder)" in summary["error"].tolist()[1]
    assert summary["frames"].astype(str).tolist() == ["3", "", "3"]
    assert not (out / "broken.csv").exists()


def test_many_recordings_write_keypoints_and_overlays_per_recording(recs, tmp_path):
    """--keypoints and --overlay with several recordings are folders: NAME.csv and NAME/ each, the same
    keypoints as tracking each alone (they were refused, so the stills of `import --each` needed a loop)."""
    out, kps, ovs = tmp_path / "out", tmp_path / "kps", tmp_path / "ovs"
    r = _run(["track", recs / "a", recs / "b", "-o", out, "--keypoints", kps, "--overlay", ovs,
              "--overlay-every", "1", "--no-check-hand"])
    assert r.exit_code == 0, r.output
    for name in ("a", "b"):
        _same_tracking(out / f"{name}.csv", recs / f"{name}-alone.csv")
        alone = tmp_path / f"{name}-kp.csv"
        assert _run(["track", recs / name, "-o", tmp_path / f"{name}.csv", "--keypoints", alone,
                     "--no-check-hand"]).exit_code == 0
        got, want = pd.read_csv(kps / f"{name}.csv", comment="#"), pd.read_csv(alone, comment="#")
        pd.testing.assert_frame_equal(got, want)
        assert sorted(p.name for p in (ovs / name).iterdir()) == [f"overlay_{i:06d}.png" for i in range(3)]
    # run again: every per-recording output exists and is never overwritten
    r = _run(["track", recs / "a", recs / "b", "-o", tmp_path / "out2", "--keypoints", kps, "--no-check-hand"])
    assert r.exit_code == 2 and "a.csv: exists and is never overwritten" in r.stderr, r.output
    r = _run(["track", recs / "a", recs / "b", "-o", tmp_path / "out3", "--overlay", ovs, "--no-check-hand"])
    assert r.exit_code == 2 and "holds overlay PNGs already" in r.stderr, r.output
    assert not (tmp_path / "out2" / "a.csv").exists() and not (tmp_path / "out3" / "a.csv").exists()


def test_batch_refusals(recs, tmp_path):
    """Outputs that would collide or be overwritten, and the per-recording options, are refused
    before anything is tracked."""
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "a").symlink_to(recs / "a")
    r = _run(["track", recs / "a", tmp_path / "x" / "a", "-o", tmp_path / "o1"])
    assert r.exit_code == 2 and "has the same name as" in r.stderr, r.output
    r = _run(["track", recs / "a", recs / "b", "-o", tmp_path / "o2", "--rerun", tmp_path / "v.rrd"])
    assert r.exit_code == 2 and r.stderr.startswith("error: --rerun: is for one recording"), r.output
    (tmp_path / "o3").mkdir()
    (tmp_path / "o3" / "b.csv").write_text("earlier\n")
    r = _run(["track", recs / "a", recs / "b", "-o", tmp_path / "o3"])
    assert r.exit_code == 2 and "b.csv: exists and is never overwritten" in r.stderr, r.output
    assert not (tmp_path / "o3" / "a.csv").exists() and (tmp_path / "o3" / "b.csv").read_text() == "earlier\n"


@pytest.mark.slow
def test_batch_reports_the_other_hand(recs, tmp_path):
    """A recording tracked as the wrong hand is flagged in the table, warned about after it and recorded in
    the summary (the single-recording warning was lost in batch runs); the summary table fits 80 columns."""
    out = tmp_path / "out"
    r = CliRunner().invoke(app, ["track", str(recs / "a"), str(recs / "b"), "-o", str(out), "--hand", "right"],
                           env={"SYNERGY_PATH": "", "COLUMNS": "80"})
    assert r.exit_code == 0, r.output
    summary = pd.read_csv(out / "summary.csv", keep_default_na=False)
    # b (palm, fingers spread) tells the hands apart clearly; each row's flag agrees with its check's text
    assert summary["other_hand_better"].tolist()[1] == True, summary  # noqa: E712 (a numpy bool)
    assert "left hand fits clearly better" in summary["hand_check"][1]
    for flag, text in zip(summary["other_hand_better"], summary["hand_check"]):
        assert bool(flag) == ("clearly better" in text), (flag, text)
    assert r.output.count("warning: ") == int(summary["other_hand_better"].sum()), r.output
    assert "other" in r.output and "warning: b: score" in " ".join(r.output.split())
    assert max(len(line) for line in r.output.splitlines()) <= 80, r.output
