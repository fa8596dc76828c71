"""Where the tracker commands write and what they read back: an output never goes into an input (even
with --overwrite), results and keypoints of another recording are refused, an invalid --mode or an
output folder that takes no files is said as such, and the many-recordings table stays readable."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from handmodel.dofs import DOF_NAMES
from tracker.cli import app
from tracker.io.tracking_file import FRAME_COLUMNS, tracking_csv
from tracker.track_cli import _short


def _cli(*args, env=None):
    return CliRunner().invoke(app, [str(a) for a in args], env=env)


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    from tracker.sim.synthesize import synthesize

    d = tmp_path_factory.mktemp("outputs") / "rec"
    synthesize("open-close", "kinect1", None, d, frames=2)
    return d


def _one_error(r, *parts):
    """Exit 2, one line on stderr holding every part, nothing on stdout."""
    assert r.exit_code == 2, r.output
    assert r.stderr.count("\n") == 1 and r.stderr.startswith("error: "), r.stderr
    for p in parts:
        assert p in r.stderr, r.stderr
    assert r.stdout == ""


def _snapshot(folder):
    return {p: p.read_bytes() for p in sorted(Path(folder).rglob("*")) if p.is_file()}


def _results(rec, path, **header):
    """A tracking output holding the recording's own truth (so it evaluates to zero error)."""
    truth = pd.read_csv(rec / "truth.csv")
    n = len(truth)
    df = pd.DataFrame({"frame": range(n), "time_s": truth["time_s"], "status": "tracked", "fit_mm": 1.0,
                       "points_used": 100, "points": 100, "ms": 10.0})
    df = pd.concat([df, truth[list(DOF_NAMES)]], axis=1)[[*FRAME_COLUMNS, *DOF_NAMES]]
    path.write_text(tracking_csv(df, {**header, "units": "metres, radians"}))
    return df


@pytest.mark.parametrize("args", [
    ("track", "{rec}", "-o", "{rec}/recording.yaml"),
    ("track", "{rec}", "-o", "{tmp}/t.csv", "--keypoints", "{rec}/depth/000000.png"),
    ("track", "{rec}", "-o", "{tmp}/t.csv", "--overlay", "{rec}/depth"),
    ("track", "{rec}", "-o", "{tmp}/t.csv", "--overlay", "{rec}"),
    ("track", "{rec}", "-o", "{tmp}/t.csv", "--rerun", "{rec}/x.rrd"),
    ("track", "{rec}", "-o", "{tmp}/t.csv", "--save-hand", "{rec}/truth_hand.yaml"),
    ("track", "{rec}", "{tmp}/other", "-o", "{rec}"),
    ("show", "{rec}", "-o", "{rec}/depth/000000.png"),
    ("show", "{tmp}/../{tmpname}/link", "-o", "{rec}/depth/000001.png"),
    ("calibrate", "{rec}", "-o", "{rec}/recording.yaml"),
    ("eval", "{rec}", "{rec}/truth.csv", "--plot", "{rec}/depth/000000.png"),
])
@pytest.mark.parametrize("overwrite", [False, True])
def test_an_output_never_goes_into_an_input(rec, tmp_path, args, overwrite):
    """`track rec -o rec/recording.yaml --overwrite` replaced the recording's metadata with the CSV,
    `show rec -o rec/depth/000000.png --overwrite` a depth frame: refused, with or without --overwrite,
    also through a symbolic link, and the recording is left as it was."""
    (tmp_path / "link").symlink_to(rec)
    before = _snapshot(rec)
    argv = [a.format(rec=rec, tmp=tmp_path, tmpname=tmp_path.name) for a in args]
    r = _cli(*argv, *(["--overwrite"] if overwrite else []))
    _one_error(r, "an input", "write it elsewhere")
    assert _snapshot(rec) == before


def test_eval_plot_over_its_results_is_refused(rec, tmp_path):
    res = tmp_path / "res.csv"
    _results(rec, res, recording=str(rec), handedness="left")
    text = res.read_text()
    _one_error(_cli("eval", rec, res, "--plot", res, "--overwrite"), str(res), "--plot is an input")
    assert res.read_text() == text


def test_a_metadata_error_shows_a_short_value(rec, tmp_path):
    """A CSV written over recording.yaml made `tracker info` print a 4 kB line holding the whole CSV."""
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "recording.yaml").write_text("frame,time_s," + ",".join(DOF_NAMES) + ",0" * 2000 + "\n")
    r = _cli("info", bad)
    _one_error(r, f"{bad / 'recording.yaml'}: schema violation", "…' is not of type 'object'")
    assert len(r.stderr) - len(str(bad)) < 200  # the value cut to 80 characters, not the 4 kB


def test_eval_refuses_results_of_another_recording(rec, tmp_path):
    """Only the frame count was checked: results of another recording of the same length were scored."""
    res = tmp_path / "res.csv"
    _results(rec, res, recording="/elsewhere/other-take", handedness="left")
    _one_error(_cli("eval", rec, res), f"{res}: was tracked on recording /elsewhere/other-take, not on {rec}",
               "--no-check-recording")
    _results(rec, res, recording="/elsewhere/rec", handedness="right")  # the same name, the other hand
    _one_error(_cli("eval", rec, res), "was tracked as a right hand", "is a left hand")
    r = _cli("eval", rec, res, "--no-check-recording")
    assert r.exit_code == 0, r.output
    # its own results, tracked from another working folder, and an older file without the header lines
    for header in ({"recording": f"../x/{rec.name}", "handedness": "left"}, {}):
        _results(rec, res, **header)
        r = _cli("eval", rec, res)
        assert r.exit_code == 0 and "posture_error_mean_deg" in r.stdout, r.output


def test_keypoints_name_their_recording_and_show_checks_it(rec, tmp_path, hand):
    """The keypoints CSV had no header, so `show --keypoints` drew another recording's skeletons; its
    one writer now names the recording and hand, its one reader gives them back (and still reads a
    header-less file)."""
    from tracker.io.tracking_file import keypoints_table, read_keypoints, write_keypoints

    df = _results(rec, tmp_path / "res.csv")
    kp = tmp_path / "kp.csv"
    write_keypoints(kp, hand, df, {"recording": "takes/other", "handedness": "left", "mode": "full"})
    assert kp.read_text().startswith("# recording: takes/other\n# handedness: left\nframe,")
    table, meta = read_keypoints(kp, hand.keypoint_names)
    assert meta == {"recording": "takes/other", "handedness": "left"} and len(table) == len(df)
    _one_error(_cli("show", rec, "-o", tmp_path / "s.png", "--keypoints", kp), f"{kp}: was tracked on recording "
               "takes/other")
    assert not (tmp_path / "s.png").exists()
    r = _cli("show", rec, "-o", tmp_path / "s.png", "--keypoints", kp, "--no-check-recording")
    assert r.exit_code == 0, r.output
    write_keypoints(kp, hand, df, {"recording": str(rec), "handedness": "right"}, overwrite=True)
    _one_error(_cli("show", rec, "-o", tmp_path / "h.png", "--keypoints", kp), "was tracked as a right hand")
    keypoints_table(hand, df).to_csv(kp, index=False)  # as written before the header
    r = _cli("show", rec, "-o", tmp_path / "old.png", "--keypoints", kp)
    assert r.exit_code == 0, r.output
    assert "2 of 2 frames shown" in " ".join(r.stdout.replace("│", " ").split())


def test_track_writes_the_keypoints_header(rec, tmp_path):
    r = _cli("track", rec, "-o", tmp_path / "t.csv", "--keypoints", tmp_path / "kp.csv", "--no-check-hand",
             "--no-safety-net", "--hand-scale", "1")
    assert r.exit_code == 0, r.output
    assert (tmp_path / "kp.csv").read_text().startswith(f"# recording: {rec}\n# handedness: left\nframe,")


def test_an_invalid_mode_is_named_before_the_synergies(rec, tmp_path):
    """`--mode foo` said `--synergies: mode 'foo' needs a synergy bundle`."""
    for extra in ([], ["-s", "fingerfist"]):
        r = _cli("track", rec, "--mode", "foo", *extra, "-o", tmp_path / "t.csv")
        assert r.stderr == "error: --mode: must be full, reduced or hierarchical, got 'foo'\n", r.output
        assert r.exit_code == 2
    # a variance out of range is named as the option, not as the PCA's n_components
    r = _cli("track", rec, "--mode", "reduced", "-s", "fingerfist", "--variance", "1.5", "-o", tmp_path / "t.csv")
    assert r.stderr == "error: --variance: must be a fraction in (0, 1), got 1.5\n" and r.exit_code == 2, r.output
    r = _cli("track", rec, "--mode", "reduced", "-s", "fingerfist", "--pcs", "3", "--variance", "0.5", "-o",
             tmp_path / "t.csv")
    assert r.stderr == "error: --pcs: give --pcs or --variance, not both (got 3 and 0.5)\n" and r.exit_code == 2
    assert not (tmp_path / "t.csv").exists()


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc (a folder that takes no files)")
def test_an_output_in_a_folder_that_takes_no_files(rec, tmp_path):
    """`-o /proc/out.csv` said `no such file or folder` of a folder that is there."""
    for argv in (["track", rec, "-o", "/proc/out.csv"], ["show", rec, "-o", "/proc/out.png"],
                 ["import", tmp_path, "--camera", "sr305", "-o", "/proc/rec"]):
        r = _cli(*argv)
        _one_error(r, "cannot be created there: the folder /proc exists but takes no new files")
        assert "no such file" not in r.stderr


def _many_names_table(tmp_path, columns):
    """The table of ``tracker track`` on two recordings of one session at ``columns`` columns: its lines."""
    from tracker.sim.synthesize import synthesize

    names = ["20210326-230536_110", "20210326-231615_0"]
    for name in names:
        synthesize("open-close", "kinect1", None, tmp_path / name, frames=1)
    r = _cli("track", *(tmp_path / n for n in names), "-o", tmp_path / "out", "--no-check-hand",
             "--no-safety-net", "--hand-scale", "1", env={"COLUMNS": str(columns)})
    assert r.exit_code == 0, r.output
    lines = r.stdout.splitlines()
    assert max(map(len, lines)) <= columns
    return names, lines


def test_many_recordings_table_keeps_names_on_one_line(tmp_path):
    """Several recordings: the name column was folded to 9 characters a line (3 lines a name) and the
    table had no fps; now each name is one line and the table fits 100 columns."""
    names, lines = _many_names_table(tmp_path, 100)
    head = next(line for line in lines if "name" in line)
    assert "fps" in head.split()
    for name in names:
        row = next(line for line in lines if name in line)  # the whole name on one line …
        cells = [c.strip() for c in row.strip("│").split("│")]
        fps = float(cells[[c.strip() for c in head.strip("┃").split("┃")].index("fps")])
        assert np.isfinite(fps) and fps > 0  # … and its rate


@pytest.mark.parametrize("slow", [False, True])
def test_narrow_terminal_keeps_the_end_of_each_name(tmp_path, monkeypatch, slow):
    """At 80 columns the names of one session's recordings were cut at the end, all alike
    ("20210326-23…"); cut in the middle, each keeps the part that tells them apart. ``slow``: the times
    as wide as they get (12345 ms a frame, 10000 fps): a loaded machine's 4-digit times had the name's
    minimum width push the header "result" off the table (CI)."""
    from tracker import batch

    real = batch.track_many
    # the times fixed, so the name's width is too: as wide as they get, or as narrow (8.2 ms, 99.9 fps)
    ms, fps = (12345.0, 10000.0) if slow else (8.2, 99.9)

    def timed_many(*a, **kw):
        table = real(*a, **kw)
        return table.assign(median_ms=ms, wall_s=table["frames"] / fps)

    monkeypatch.setattr(batch, "track_many", timed_many)
    _, lines = _many_names_table(tmp_path, 80)
    firsts = [line.strip("│ ").split("│")[0].strip() for line in lines if "…" in line and "│" in line]
    assert len(firsts) == 2 and firsts[0].endswith("_110") and firsts[1].endswith("_0") and firsts[0] != firsts[1]
    if not slow:
        # the cut falls in the date both names share, so each keeps its take's own digits whole (a new user
        # read "202…15_140" and "202…36_110": the takes 230536 and 231615 cut to their last two digits)
        assert "0536_110" in firsts[0] and "1615_0" in firsts[1], firsts
    # only the names are cut: every header and number is whole (the ms column was cut to "3008…")
    head = next(line for line in lines if "name" in line)
    assert "…" not in head and {"frames", "tracked", "reinit", "ms", "fps", "result"} <= set(head.strip("┃ ").replace("┃", " ").split())
    assert all("…" not in cell for line in lines if "│" in line for cell in line.strip("│ ").split("│")[1:])
    assert [_short(x) for x in (8.25, 99.94, 3008.4, 123456.0)] == ["8.2", "99.9", "3008", "123456"]


def test_threads_change_the_time_not_the_result(rec, tmp_path):
    """``--threads`` runs a start search's fits side by side: the tracked θ are the same as on one
    thread; a negative count is refused."""
    outs = []
    for n in (1, 2):
        out = tmp_path / f"t{n}.csv"
        r = _cli("track", rec, "-o", out, "--threads", n, "--no-check-hand")
        assert r.exit_code == 0, r.output
        outs.append(pd.read_csv(out, comment="#"))
    pd.testing.assert_frame_equal(outs[0][list(DOF_NAMES)], outs[1][list(DOF_NAMES)], check_exact=True)
    assert set(outs[0]["status"]) <= {"tracked", "reinit"}
    r = _cli("track", rec, "-o", tmp_path / "t.csv", "--threads", -1)
    assert r.exit_code == 2 and "--threads" in r.output


def test_overwrite_leaves_no_overlay_of_an_earlier_run(rec, tmp_path):
    """With --overwrite, the overlays of frames this run did not draw (an earlier run's, other settings)
    are removed after the run; files that are not overlays stay."""
    figs = tmp_path / "figs"
    base = ("track", rec, "-o", tmp_path / "t.csv", "--overlay", figs, "--no-check-hand", "--no-safety-net",
            "--hand-scale", "1", "--threads", "1")
    r = _cli(*base, "--overlay-every", "1")
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in figs.iterdir()) == ["overlay_000000.png", "overlay_000001.png"]
    (figs / "notes.png").write_bytes(b"mine")
    (figs / "overlay_best.png").write_bytes(b"mine too")
    r = _cli(*base, "--overlay-every", "2", "--overwrite")
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in figs.iterdir()) == ["notes.png", "overlay_000000.png", "overlay_best.png"]


def test_an_unreadable_frame_is_lost_and_the_run_goes_on(tmp_path):
    """A frame file cut short in the middle of a recording folder: the frames after it are tracked, the
    outputs hold every frame (that one lost), and the command then fails naming the file (exit 2);
    many recordings: its summary row says so."""
    import shutil

    from tracker.io.tracking_file import read_tracking
    from tracker.sim.synthesize import synthesize

    rec = tmp_path / "rec"
    synthesize("open-close", "kinect1", None, rec, frames=3)
    bad = rec / "depth" / "000001.png"
    bad.write_bytes(bad.read_bytes()[:300])
    args = ("--no-check-hand", "--no-safety-net", "--hand-scale", "1", "--threads", "1")
    r = _cli("track", rec, "-o", tmp_path / "t.csv", "--keypoints", tmp_path / "k.csv", *args)
    assert r.exit_code == 2, r.output
    assert "000001.png: unreadable PNG" in r.stderr and "1 of 3 frames unreadable, tracked as lost" in r.stderr
    df, _ = read_tracking(tmp_path / "t.csv")
    assert df["status"].tolist()[1] == "lost" and df["status"].tolist()[2] != "lost" and len(df) == 3
    # the unreadable frame has no θ and no keypoints (they repeated the frame before it)
    dofs = [c for c in df.columns if c.endswith(("_flex", "_abd")) or c in ("tx", "ty", "tz", "rx", "ry", "rz")]
    assert dofs and df.loc[1, dofs].isna().all() and df.loc[0, dofs].notna().all()
    kp = pd.read_csv(tmp_path / "k.csv", comment="#")
    xyz = [c for c in kp.columns if c.endswith(("_x_mm", "_y_mm", "_z_mm"))]
    assert xyz and kp.loc[kp["frame"] == 1, xyz].isna().all().all() and kp.loc[kp["frame"] == 0, xyz].notna().all().all()
    other = tmp_path / "other"
    shutil.copytree(rec, other)
    r = _cli("track", rec, other, "-o", tmp_path / "many", *args)
    assert r.exit_code == 2, r.output
    summary = pd.read_csv(tmp_path / "many" / "summary.csv")
    assert summary["error"].str.contains("1 of 3 frames unreadable").all()
    assert (tmp_path / "many" / "rec.csv").is_file() and (tmp_path / "many" / "other.csv").is_file()


@pytest.mark.parametrize("option, value, said", [("--depth-range", "300,1000", "0.3,1"),
                                                 ("--box", "-100,,,500,,", "-0.1,,,0.5,,")])
def test_millimetres_for_metres_are_refused(rec, tmp_path, option, value, said):
    """A depth range or box in millimetres looked for the hand hundreds of metres away: every frame was
    lost as if there were no hand, with the camera preset blamed. Now one line says the unit."""
    r = _cli("track", rec, "-o", tmp_path / "t.csv", f"{option}={value}")
    assert r.exit_code == 2, r.output
    assert f"{option}: values are in metres" in r.stderr and f"if you meant millimetres: {said})" in r.stderr
    assert "Traceback" not in r.output and not (tmp_path / "t.csv").exists()


def test_an_overlay_step_below_one_is_refused(rec, tmp_path):
    r = _cli("track", rec, "-o", tmp_path / "t.csv", "--overlay", tmp_path / "ov", "--overlay-every", "0")
    assert r.exit_code == 2 and "--overlay-every: must be ≥ 1 (1 = every frame), got 0" in r.stderr, r.output
    assert not (tmp_path / "t.csv").exists() and not (tmp_path / "ov").exists()
