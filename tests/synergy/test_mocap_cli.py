"""End to end: synergy simulate → C3D → synergy angles / synergy fit --per-task → compare."""
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from handmodel import HandModel
from synergy.angles import markers_to_angles, read_angles_csv
from synergy.c3d import read_c3d, task_from_events
from synergy.cli import app

runner = CliRunner()
HAND = HandModel.load()


@pytest.fixture(scope="module")
def mocap(tmp_path_factory):
    out = tmp_path_factory.mktemp("mocap")
    r = runner.invoke(app, ["simulate", "-o", str(out), "--motions", "open_close,power_grasp,precision_grasp",
                            "--trials", "1", "--duration", "2", "--noise-mm", "0", "--gaps", "0", "--units", "cm",
                            "--prefix", "Subj"])
    assert r.exit_code == 0, r.output
    return out


def test_simulated_c3d_round_trip(mocap):
    data = read_c3d(mocap / "power_grasp_01.c3d")
    assert data.units == "cm" and data.original_labels[0].startswith("Subj:") and data.labels[0] == "WRR"
    assert task_from_events(data) == "grasp"
    truth = pd.read_csv(mocap / "truth" / "power_grasp_01.csv", comment="#")
    df = markers_to_angles(data, "hand16")
    err = np.degrees(np.sqrt(np.mean((df[HAND.dof_names[6:]].to_numpy() - truth[HAND.dof_names[6:]].to_numpy()) ** 2)))
    assert err <= 0.05


def test_angles_command_writes_tables_and_refuses_overwrite(mocap, tmp_path):
    files = sorted(str(p) for p in mocap.glob("open_close_*.c3d"))
    r = runner.invoke(app, ["angles", *files, "--markers", "hand16", "-o", str(tmp_path)])
    assert r.exit_code == 0, r.output
    assert "residual" in r.output
    df = read_angles_csv(tmp_path / "open_close_01.csv")
    assert len(df) == 200 and df.attrs["markerset"] == "hand16"
    r = runner.invoke(app, ["angles", *files, "--markers", "hand16", "-o", str(tmp_path)])
    assert r.exit_code == 2 and "never overwritten" in r.output


def test_angles_chooses_the_marker_set_and_hand_as_fit_does(mocap, tmp_path):
    """Without --markers and --hand, angles reads a trial with the set its labels fit and the hand they
    name, as synergy fit does (it required --markers and took the left hand: the real DFKI glove trial
    stopped with 'the right hand fits these markers better')."""
    from pathlib import Path

    from synergy.fit import _choose

    f = mocap / "power_grasp_01.c3d"
    ms, hand, rep = _choose(read_c3d(f), Path(f), None, None, "trial", True, None)
    r = runner.invoke(app, ["angles", str(f), "-o", str(tmp_path / "auto")])
    assert r.exit_code == 0, r.output
    assert f"marker IK ({ms.name}, {hand} hand;" in r.output
    r = runner.invoke(app, ["angles", str(f), "--markers", ms.name, "--hand", hand, "-o", str(tmp_path / "given")])
    assert r.exit_code == 0, r.output
    auto, given = read_angles_csv(tmp_path / "auto" / f"{f.stem}.csv"), read_angles_csv(tmp_path / "given" / f"{f.stem}.csv")
    pd.testing.assert_frame_equal(auto, given)
    r = runner.invoke(app, ["angles", str(f), "--hand", "both", "-o", str(tmp_path / "bad")])
    assert r.exit_code == 2 and "--hand: must be left or right" in r.output


def test_angles_table_keeps_each_trial_on_one_line_at_100_columns(mocap, tmp_path):
    # a folded name took 3 lines of the table; each trial is one line now, and a name too long for its
    # column keeps its start and its distinguishing end; the file written keeps the full path
    src = tmp_path / "in"
    src.mkdir()
    fits = src / "ART-Human_hands_real_no6dof_copy.c3d"
    long = src / "subject_07_session_2026-03-14_power_grasp_right_hand_trial_01.c3d"
    for f in (fits, long):
        f.write_bytes((mocap / "open_close_01.c3d").read_bytes())
    r = runner.invoke(app, ["angles", str(fits), str(long), "--markers", "hand16", "-o", str(tmp_path / "out")],
                      env={"COLUMNS": "100"})
    assert r.exit_code == 0, r.output
    table = [ln for ln in r.stdout.splitlines() if ln.startswith(("┃", "│", "┏", "┡", "└"))]
    assert max(len(ln) for ln in table) <= 100
    rows = [ln for ln in table if ln.startswith("│")]
    assert len(rows) == 2, r.stdout
    assert rows[0].startswith(f"│{fits.name} ")  # whole
    cells = [c.strip() for c in rows[1].strip("│").split("│")]
    assert cells[0].startswith("subject_07_session") and "…" in cells[0] and cells[0].endswith("trial_01.c3d")
    assert cells[-2] == "good" and int(cells[1]) == 200  # the numbers whole beside it
    assert read_angles_csv(tmp_path / "out" / f"{long.stem}.csv").attrs["source"] == str(long)


def test_per_task_bundles_differ(mocap, tmp_path):
    files = sorted(str(p) for p in mocap.glob("*.c3d"))
    r = runner.invoke(app, ["fit", *files, "--markers", "hand16", "--name", "sim", "--per-task", "-o", str(tmp_path)])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "sim-grasp-1.0.0.npz").exists() and (tmp_path / "sim-general-1.0.0.npz").exists()
    r = runner.invoke(app, ["compare", "sim-grasp", "sim-general", "-r", str(tmp_path)])
    assert r.exit_code == 0, r.output
    from synergy.bundle import load_bundle
    from synergy.pca_analysis import principal_angles

    a = load_bundle("sim-grasp", [tmp_path]).model
    b = load_bundle("sim-general", [tmp_path]).model
    ang = np.degrees(principal_angles(a, b, 3))
    assert ang.max() > 20  # the grasp and general synergy subspaces differ


def test_bad_inputs_exit_2_with_one_line(tmp_path):
    bad = tmp_path / "broken.c3d"
    bad.write_bytes(b"\x00" * 100)
    r = subprocess.run([sys.executable, "-m", "synergy.cli", "angles", str(bad), "--markers", "hand16", "-o",
                        str(tmp_path / "o")], capture_output=True, text=True)
    assert r.returncode == 2 and "Traceback" not in r.stderr and "broken.c3d" in r.stderr
    r = subprocess.run([sys.executable, "-m", "synergy.cli", "simulate", "-o", str(tmp_path), "--motions", "dance"],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "unknown motion" in r.stderr


COMMANDS = {"angles": ["-o", "out"], "fit": ["--name", "t", "-o", "."],
            "calibrate": ["--markers", "hand19", "-o", "s.yaml"]}


@pytest.mark.parametrize("command, make, problem", [
    ("angles", lambda p: p.write_bytes(b"this is not a c3d file at all\n"), "not a C3D file (it is text)"),
    ("fit", lambda p: p.write_bytes(b"this is not a c3d file at all\n"), "not a C3D file (it is text)"),
    ("calibrate", lambda p: p.write_bytes(b"this is not a c3d file at all\n"), "not a C3D file (it is text)"),
    ("fit", lambda p: p.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(3000)), "not a C3D file (it is a PNG image)"),
    ("calibrate", lambda p: p.write_bytes(bytes(4096)), "not a C3D file (header key byte is 0x00, expected 0x50)"),
    ("angles", lambda p: p.write_bytes(b"\x02\x50" + bytes(200)),
     "truncated: 202 bytes, shorter than the 512-byte header"),
    ("fit", lambda p: p.write_bytes(b""), "empty file (0 bytes)"),
    ("angles", lambda p: p.mkdir(), "not a regular file"),
    ("calibrate", lambda p: p.mkdir(), "not a regular file"),
], ids=["text-angles", "text-fit", "text-calibrate", "png-fit", "zeros-calibrate", "short-header-angles", "empty-fit",
        "folder-angles", "folder-calibrate"])
def test_bad_c3d_inputs_through_the_reading_commands(tmp_path, command, make, problem):
    """angles, fit and calibrate: exit 2 and one line, ``error: <file>: <problem>``, in our words."""
    bad = tmp_path / "x.c3d"
    make(bad)
    r = subprocess.run([sys.executable, "-m", "synergy.cli", command, str(bad), *COMMANDS[command]],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 2 and r.stdout == "" and r.stderr == f"error: {bad}: {problem}\n", r.stderr


def test_damaged_real_c3d_through_the_cli(tmp_path):
    """A real trial cut short (py-c3d failed on its 2-D TRIAL fields with "only 0-dimensional arrays can be
    converted", ezc3d's reason came second) and one whose parameters overrun (ezc3d's "iostream error",
    py-c3d's "unpack requires a buffer"): each says what is wrong with the file."""
    from conftest import shared

    cut = tmp_path / "cut.c3d"
    cut.write_bytes(shared("c3dorg_art_hands", "ART-Human_hands_real_no6dof.c3d").read_bytes()[:20_000])
    overrun = tmp_path / "overrun.c3d"
    overrun.write_bytes(shared("btk_samples", "others__badParameterOffset.c3d").read_bytes())
    for f, problem in ((cut, "truncated: 969 frames announced, 16 whole frames stored and 288 bytes of a partial "
                             "frame"),
                       (overrun, "corrupt parameter section: parameter LABELS is 429 bytes long but its offset to the "
                                 "next entry is 416")):
        r = subprocess.run([sys.executable, "-m", "synergy.cli", "angles", str(f), "-o", str(tmp_path / "out")],
                           capture_output=True, text=True)
        assert r.returncode == 2 and r.stderr == f"error: {f}: {problem}\n", r.stderr
