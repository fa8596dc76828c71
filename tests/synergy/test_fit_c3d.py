"""`synergy fit` on C3D trials: the marker set and hand chosen from the labels (simulated hand16 and
hand19 trials, the real ART and DFKI files), the closest sets when none fits, the per-trial
conversion table, and poor trials refused unless --accept-poor."""
import io
import re

import numpy as np
import pytest
from typer.testing import CliRunner

from conftest import shared
from synergy.c3d import read_c3d
from synergy.c3d_write import write_c3d
from synergy.calibrate import Calibration, save_calibration
from synergy.cli import app
from synergy.errors import MarkerSetError
from synergy.fit import read_trial
from synergy.markers import choose_markerset, load_markerset, shipped_markersets

runner = CliRunner()


def simulate(out, *args):
    """One tiny simulated power grasp (50 frames): conversions stay cheap."""
    r = runner.invoke(app, ["simulate", "-o", str(out), "--motions", "power_grasp", "--trials", "1",
                            "--duration", "0.5", *args])
    assert r.exit_code == 0, r.output
    return out / "power_grasp_01.c3d"


@pytest.fixture(scope="module")
def sims(tmp_path_factory):
    root = tmp_path_factory.mktemp("sims")
    return {"hand16": simulate(root / "h16"), "hand19": simulate(root / "h19", "--markers", "hand19")}


@pytest.fixture(scope="module")
def right_trial(tmp_path_factory):
    return simulate(tmp_path_factory.mktemp("right"), "--hand", "right")


@pytest.fixture(scope="module")
def sets():
    return shipped_markersets()


def test_choice_from_simulated_labels(sets):
    for name in ("hand16", "hand19"):
        labels = ["Subj:" + m.label for m in load_markerset(name).markers] + ["Subj:ELBOW"]
        ms, hand, rep = choose_markerset(labels, sets)
        n = len(ms.markers)
        # hand16 and hand19 share 15 labels: each file must pick its own set, not the other
        assert (ms.name, hand, rep["matched"], rep["total"], rep["unused"]) == (name, None, n, n, 1)


def test_choice_from_real_files(sets):
    art = read_c3d(shared("c3dorg_art_hands", "ART-Human_hands_real_no6dof.c3d"))
    ms, hand, rep = choose_markerset(list(art.labels), sets)
    # both hands are in the file: left is taken, the right named; body points are ignored labels
    assert (ms.name, hand, rep["matched"], rep["unused"]) == ("art-joint-centres", "left", 21, 0)
    assert rep["others"] == [{"name": "art-joint-centres", "hand": "right"}]
    assert choose_markerset(list(art.labels), sets, hand="right")[1] == "right"
    glove = read_c3d(shared("dfki_hand_embodiment", "DERIVED_recording_tsv_to.c3d"))
    ms, hand, rep = choose_markerset(list(glove.labels), sets)
    assert (ms.name, hand, rep["matched"]) == ("dfki-glove13", None, 13)
    # ART's 6-DoF limb export carries no finger points: no set fits
    limbs = read_c3d(shared("c3dorg_art_hands", "ART-Human_tools_integer_6dofLimbs.c3d"))
    with pytest.raises(MarkerSetError, match=r"no marker set fits its labels: closest art-joint-centres left "
                                             r"\(1 of 21; missing LTIN"):
        choose_markerset(list(limbs.labels), sets, where="limbs.c3d")


def test_no_fit_names_three_closest_sets(sets):
    labels = [m.label for m in load_markerset("hand16").markers if m.label not in ("MC3", "INAIL")]
    with pytest.raises(MarkerSetError) as e:
        choose_markerset(labels, sets, where="t.c3d")
    msg = str(e.value)
    assert msg.startswith("t.c3d: no marker set fits its labels: closest hand16 (14 of 16; missing MC3, INAIL)")
    # hand19 lacks its four proximal-phalanx markers and INAIL; three sets named, no more
    assert "hand19 (14 of 19; missing IPP, INAIL, MPP, RPP, ...)" in msg and msg.count(" of ") == 3


def test_wrong_hand_found_by_the_handedness_check(right_trial):
    # side-less labels cannot tell the hands apart: the check does, and the conversion is good
    t = read_trial(right_trial, calibration=None)
    c = t.conversion
    assert (c["markerset"], c["hand"], c["hand_from"], c["verdict"]) == ("hand16", "right", "handedness check", "good")
    assert c["residual_median_mm"] < 1.0


def _lines(out):
    return [ln for ln in out.splitlines() if ln.strip()]


def test_fit_chooses_sets_and_prints_quality_table(sims, tmp_path):
    r = runner.invoke(app, ["fit", str(sims["hand16"]), str(sims["hand19"]), "--name", "auto", "-o", str(tmp_path),
                            "--no-hand-check"])
    assert r.exit_code == 0, r.output
    out = r.output
    assert "marker set hand16, hand left (16 of 16 labels matched): power_grasp_01.c3d" in out
    assert "marker set hand19, hand left (19 of 19 labels matched): power_grasp_01.c3d" in out
    rows = [ln for ln in _lines(out) if "power_grasp_01.c3d" in ln and "hand1" in ln and "│" in ln]
    assert len(rows) == 2
    for row, name in zip(rows, ("hand16 L", "hand19 L")):
        cells = [c.strip() for c in row.strip("│").split("│")]
        assert cells[1] == name and cells[-1] == "good"
        med, p95, ok = (float(x) for x in cells[2:5])  # numbers whole, not cut by the table
        assert 0 < med <= p95 < 2.0 and ok == 100.0
    assert max(len(ln) for ln in out.splitlines() if "│" in ln or "┃" in ln) <= 80
    assert (tmp_path / "auto-1.0.0.npz").exists()


def test_print_names_the_other_hand_of_a_two_handed_file():
    from rich.console import Console

    from synergy.cli import _print_conversions
    from synergy.fit import Trial

    conv = {"markerset": "art-joint-centres", "hand": "left", "chosen": "labels", "hand_from": "labels",
            "matched": 21, "total": 21, "others": [{"name": "art-joint-centres", "hand": "right"}],
            "residual_median_mm": 1.581, "residual_p95_mm": 12.049, "ok_share": 1.0, "verdict": "good",
            "warnings": [], "reasons": []}
    con = Console(width=80, record=True, file=io.StringIO())
    _print_conversions(con, [Trial("mocap/a_very_long_trial_name_of_a_session_2026.c3d", np.zeros((2, 20)),
                                   conversion=conv)], accept_poor=False)
    text = con.export_text()
    assert ("marker set art-joint-centres, hand left (21 of 21 labels matched); the file also carries the right "
            "hand (--hand right): a_very_long_trial_name_of_a_session_2026.c3d") in text
    assert max(len(ln) for ln in text.splitlines() if "│" in ln) <= 80
    # a long name stays on its row, cut in the middle (start and end kept); the numbers stay whole
    assert re.search(r"^│a_very_long\w*…\w*_2026\.c3d *│ *art-joint-centres L *│ *1\.58 *│ *12\.05 *│ *100\.0 *│ *good│$",
                     text, re.M), text


@pytest.fixture(scope="module")
def left_subject(tmp_path_factory):
    """A subject calibration of the left hand with hand16 that keeps the model as it is (the simulator's
    subject is the default hand): it names the set and hand, and skips per-trial calibration."""
    p = tmp_path_factory.mktemp("subject") / "left.yaml"
    save_calibration(Calibration(method="none", hand="left", markerset="hand16", hand_model="default",
                                 median_residual_mm=0.0), p)
    return p


def test_poor_trial_refused_then_accepted(right_trial, left_subject, tmp_path):
    f = right_trial  # a right hand converted as the subject's left hand
    r = runner.invoke(app, ["fit", str(f), "--name", "poor", "-o", str(tmp_path), "--subject", str(left_subject)])
    assert r.exit_code == 2, r.output
    lines = _lines(r.output)
    assert re.search(r"power_grasp_01\.c3d\s*│\s*hand16 L\s*│.*│\s*poor\s*│", r.output)
    assert lines[-1].startswith(f"error: {f.as_posix()}: poor conversion (hand16, left hand): the right hand fits "
                                "these markers better")
    assert lines[-1].endswith("(--accept-poor fits it anyway)") and "Traceback" not in r.output
    assert not list(tmp_path.glob("*.npz"))
    r = runner.invoke(app, ["fit", str(f), "--name", "poor", "-o", str(tmp_path), "--subject", str(left_subject),
                            "--accept-poor"])
    assert r.exit_code == 0, r.output
    assert "power_grasp_01.c3d: fitted despite a poor conversion (--accept-poor): the right hand fits" in r.output
    assert (tmp_path / "poor-1.0.0.npz").exists()
    # the bundle's manifest keeps the verdict with the source, sealed by its hash
    from synergy.bundle import read_bundle

    src = read_bundle(tmp_path / "poor-1.0.0.npz").manifest["sources"][0]
    assert src["conversion"]["verdict"] == "poor" and src["conversion"]["markerset"] == "hand16"
    assert src["conversion"]["hand"] == "left" and src["conversion"]["residual_median_mm"] > 0


def test_file_no_set_fits_is_one_line_exit_2(tmp_path):
    pts = np.random.default_rng(0).normal(size=(20, 5, 3)) * 0.05
    f = tmp_path / "odd.c3d"
    write_c3d(f, pts, ["A1", "A2", "WRR", "WRU", "MC2"], 100.0)
    r = runner.invoke(app, ["fit", str(f), "--name", "odd", "-o", str(tmp_path / "reg")])
    assert r.exit_code == 2
    assert len(_lines(r.output)) == 1, r.output
    line = r.output.strip()
    assert line.startswith(f"error: {f.as_posix()}: no marker set fits its labels: closest ")
    assert "closest hand16 (3 of 16; missing MC3, MC5, TMC, TPP, ...); hand19 (3 of 19;" in line and line.endswith(
        "give --markers NAME or a marker-set YAML")
    # a named set that does not fit lists every missing marker and the file's labels
    r = runner.invoke(app, ["fit", str(f), "--markers", "hand16", "--name", "odd", "-o", str(tmp_path / "reg")])
    assert r.exit_code == 2 and len(_lines(r.output)) == 1
    assert "marker set 'hand16': missing marker(s) MC3, MC5, TMC" in r.output and "the file has A1, A2, WRR" in r.output


def test_fit_dip_prior_sd_reaches_the_ik_and_the_manifest(sims, tmp_path):
    from synergy.bundle import read_bundle

    # the option is passed to the IK: with the prior off, the DIPs of this grasp come out differently
    on = read_trial(sims["hand16"], calibration=None, check_hand=False)
    off = read_trial(sims["hand16"], calibration=None, check_hand=False, dip_prior_sd=0)
    assert on.conversion["dip_prior"] == {"ratio": pytest.approx(2 / 3), "sd_deg": 10.0}
    assert off.conversion["dip_prior"] is None and np.abs(on.postures - off.postures).max() > 1e-4
    for args, sd in ((["--dip-prior-sd", "5"], 5.0), ([], 10.0), (["--dip-prior-sd", "0"], None)):
        name = f"dip{int(sd or 0)}"
        r = runner.invoke(app, ["fit", str(sims["hand16"]), "--name", name, "-o", str(tmp_path), "--no-hand-check",
                                *args])
        assert r.exit_code == 0, r.output
        rec = read_bundle(tmp_path / f"{name}-1.0.0.npz").manifest["sources"][0]["conversion"]["dip_prior"]
        assert rec == (None if sd is None else {"ratio": pytest.approx(2 / 3), "sd_deg": sd})
    r = runner.invoke(app, ["fit", str(sims["hand16"]), "--name", "bad", "-o", str(tmp_path), "--dip-prior-sd", "-2"])
    assert r.exit_code == 2 and len(_lines(r.output)) == 1 and "--dip-prior-sd" in r.output


def test_fit_refuses_a_bad_target_or_input_before_converting(tmp_path, monkeypatch):
    """What the end of `synergy fit` would refuse is refused before any file is converted (that took
    minutes): no registry, an existing --version (per task too), a truncated C3D after a good one."""
    import synergy.fit

    good = shared("c3dorg_art_hands", "ART-Human_hands_real_no6dof.c3d")
    cut = tmp_path / "cut.c3d"
    cut.write_bytes(good.read_bytes()[:500_000])
    reg = tmp_path / "reg"
    reg.mkdir()
    taken = reg / "art-1.0.0.npz"
    taken.write_bytes(b"an earlier bundle")
    (reg / "art-grasp-1.0.0.npz").write_bytes(b"an earlier bundle")
    converted = []

    def convert(f, *a, **kw):
        converted.append(f)
        raise AssertionError(f"{f} converted")

    monkeypatch.setattr(synergy.fit, "read_trial", convert)
    cases = [
        (["--name", "noreg"], "noreg: no target registry"),
        (["--name", "art", "--version", "1.0.0", "-o", str(reg)],
         f"{taken}: version 1.0.0 exists; bundle versions are immutable"),
        (["--name", "art", "--task", "grasp", "--per-task", "--version", "1.0.0", "-o", str(reg)],
         f"{reg / 'art-grasp-1.0.0.npz'}: version 1.0.0 exists"),
        (["--name", "art", "-o", str(reg), str(cut)], f"{cut}: truncated: 969 frames announced"),
    ]
    for args, line in cases:
        r = runner.invoke(app, ["fit", str(good), *args], env={"SYNERGY_PATH": ""})
        assert r.exit_code == 2, (args, r.output, r.exception)
        assert len(_lines(r.output)) == 1 and r.output.startswith(f"error: {line}"), r.output
        assert not converted
    assert taken.read_bytes() == b"an earlier bundle" and len(list(reg.iterdir())) == 2
    # the same command with a free version reaches the conversion: the patch above is what it calls
    r = runner.invoke(app, ["fit", str(good), "--name", "art", "--version", "1.0.1", "-o", str(reg)])
    assert isinstance(r.exception, AssertionError) and converted == [good]
