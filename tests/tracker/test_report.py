"""The experiments report's parts run side by side in worker processes give what they give in one."""
import numpy as np

from tracker.sim.report import STEPS, run_steps


def test_parts_in_two_workers_equal_one_by_one():
    """Two parts run in two worker processes give what they give one after the other in this process, and
    the progress is told once per part. The two are the cheapest of the report's parts (quick: occlusion
    ~1.7 s, the single frames ~1.7 s; the density sweep, compared before, ~4.5 s in each run)."""
    names = ["occlusion", "single"]
    assert set(names) <= set(STEPS)
    seen = []
    alone = run_steps(names, quick=True, jobs=1)
    both = run_steps(names, quick=True, jobs=2, progress=lambda k, n, name: seen.append((k, n, name)))
    assert sorted(seen) == [(1, 2, seen[0][2]), (2, 2, seen[1][2])] and {s[2] for s in seen} == set(names)
    assert alone["occlusion"].keys() == both["occlusion"].keys()
    for k in alone["occlusion"]:
        assert np.isclose(alone["occlusion"][k], both["occlusion"][k]), k
    # the single frames: every error and share the same to the last bit; "s_<method>" are the machine's seconds
    assert alone["single"].keys() == both["single"].keys()
    for k in alone["single"]:
        if not k.startswith("s_"):
            np.testing.assert_equal(both["single"][k], alone["single"][k], err_msg=k)


def test_real_part_needs_its_folder_and_reports_bad_labels(tmp_path):
    """`tracker experiments --only real` without --real-data, or with a folder without labels: one line, exit 2."""
    import subprocess
    import sys

    for extra, want in (([], "--real-data"), (["--real-data", str(tmp_path)], "labels.json")):
        r = subprocess.run([sys.executable, "-m", "tracker.cli", "experiments", "--only", "real", "-o",
                            str(tmp_path / "out"), *extra], capture_output=True, text=True)
        assert r.returncode == 2 and r.stderr.startswith("error: ") and r.stderr.count("\n") == 1, r.stderr
        assert want in r.stderr, r.stderr


def test_real_lines_count_the_floors():
    """The real frames' section counts a frame only when every floor holds (tips, wrist, mask)."""
    from tracker.sim.report import real_lines

    # the labelled hand lies above its wrist (rows 0-9); model wrist "a" sits 4 px into it, "b" 5 px below
    mask = np.zeros((20, 20), bool)
    mask[:10, 5:15] = True
    common = {"mask": mask, "labels": {"wrist": [10, 10]}, "names": ["wrist"], "ends_uv": np.zeros((5, 2)),
              "tip_ends_px": {}}
    good = {"name": "a", "scale": 1.2, "tips_px": {"thumb": 3.0, "index": 14.9}, "wrist_px": 19.0, "wrist_joint_px": 4.0, "in_mask": 0.95,
            "ok": True, "uv": np.array([[10.0, 6.0]]), **common}
    bad = {"name": "b", "scale": 1.2, "tips_px": {"thumb": 3.0, "index": 15.1}, "wrist_px": 5.0, "wrist_joint_px": 5.0, "in_mask": 1.0,
           "ok": False, "uv": np.array([[10.0, 15.0]]), **common}
    text = "\n".join(real_lines([good, bad]))
    assert "every floor: 1 of 2" in text and "tips within 15 px: 3 of 4" in text and "[png](real/b.png)" in text
    assert "palm side of the crease in 1 of 2 frames" in text
    assert "median 12 px apart" in text and "a median 4 px from the label" in text  # crease (19, 5), joint (4, 5)
    assert "| 19 | 4 | 95 % | yes |" in text


def test_real_lines_sum_up_the_calibrated_protocol():
    """With the rows of the hand calibrated from stills, the section adds one line: the hand of each
    recording (its first row's size and finger lengths) and the same counts, the frames off a floor named."""
    from tracker.sim.report import real_lines

    mask = np.zeros((20, 20), bool)
    mask[:10, 5:15] = True
    row = {"mask": mask, "labels": {"wrist": [10, 10]}, "uv": np.array([[10.0, 6.0]]), "in_mask": 1.0,
           "wrist_joint_px": 4.0, "names": ["wrist"], "ends_uv": np.zeros((5, 2)), "tip_ends_px": {},
           "fingers": {"thumb": 1.06, "pinky": 0.91}}
    rows = [{**row, "name": "r1_30", "scale": 1.263, "tips_px": {"thumb": 3.0}, "wrist_px": 5.0, "ok": True},
            {**row, "name": "r1_50", "scale": 1.263, "tips_px": {"thumb": 39.0}, "wrist_px": 5.0, "ok": False},
            {**row, "name": "r2_0", "scale": 1.238, "tips_px": {"thumb": 4.0}, "wrist_px": 21.0, "ok": False}]
    plain = "\n".join(real_lines(rows))
    text = "\n".join(real_lines(rows, each=rows))
    assert "calibrate --each" not in plain
    extra = text[len(plain):]
    assert "r1: size 1.263, thumb 1.06, pinky 0.91; r2: size 1.238" in extra
    assert "every floor: 1 of 3" in extra and "tips within 15 px: 2 of 3" in extra and "worst 39 px" in extra
    assert "wrist within 20 px: 2 of 3" in extra and "off a floor: r1_50, r2_0." in extra


def test_real_lines_measure_the_tips_along_the_last_bone():
    """The finger-end sentence: along each labelled finger's projected last bone, how far past its label
    the tip keypoint and the finger's end lie (signed, px); a finger pointing at the camera (its last
    bone under 8 px in the image) is left out."""
    from handmodel import HandModel
    from tracker.sim.report import real_lines

    names = HandModel.load().keypoint_names
    mask = np.zeros((40, 40), bool)
    mask[5:30, 5:30] = True
    uv = np.full((len(names), 2), 20.0)
    uv[names.index("thumb3")], uv[names.index("thumb_tip")] = (0.0, 0.0), (10.0, 0.0)  # the bone along +u
    uv[names.index("index3")], uv[names.index("index_tip")] = (0.0, 30.0), (3.0, 34.0)  # 5 px: at the camera
    ends = np.zeros((5, 2))
    ends[0], ends[1] = (15.0, 0.0), (4.0, 35.0)
    row = {"name": "r_0", "scale": 1.2, "mask": mask, "uv": uv, "names": names, "ends_uv": ends, "in_mask": 1.0,
           "labels": {"wrist": [20, 30], "thumb": [8, 3], "index": [40, 40]}, "tips_px": {"thumb": 3.6, "index": 7.2},
           "tip_ends_px": {"thumb": 7.6, "index": 6.0}, "wrist_px": 5.0, "wrist_joint_px": 5.0, "ok": True}
    text = "\n".join(real_lines([row]))
    assert "over the 1 tip not pointing at the camera" in text
    assert "the tip keypoint lies a median +2.0 px past the label" in text and "the finger's end +7.0 px" in text
    assert "tips within 15 px: 2 of 2 (median 6.8 px)" in text


def test_report_never_replaces_a_report_or_goes_into_the_real_data(tmp_path):
    """`tracker experiments` refuses a folder holding a report (without --overwrite) and an output
    inside the labelled frames' folder, before any work: one line, exit 2, the earlier report as it was."""
    import subprocess
    import sys

    data = tmp_path / "data"
    (data / "labels").mkdir(parents=True)
    (data / "labels" / "labels.json").write_text("{}")
    old = tmp_path / "old"
    old.mkdir()
    (old / "report.md").write_text("earlier\n")
    for out, want in ((old, "--overwrite"), (data / "rep", "input")):
        r = subprocess.run([sys.executable, "-m", "tracker.cli", "experiments", "--only", "real", "-o", str(out),
                            "--real-data", str(data)],
                           capture_output=True, text=True)
        assert r.returncode == 2 and r.stderr.startswith("error: ") and r.stderr.count("\n") == 1, r.stderr
        assert want in r.stderr, r.stderr
    assert (old / "report.md").read_text() == "earlier\n" and not (data / "rep").exists()
