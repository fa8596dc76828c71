"""Every command of ``tracker`` and ``synergy`` that writes a file or folder, run as a user runs it,
with an output that cannot be written: under a read-only file system, a folder where a file goes
(or a file where a folder goes), a full file system, and a nearly full one (the check passes, the
write itself runs out of space). Each must exit 2 with one plain line naming the output, print
nothing after it, leave no file under a final name and leave an earlier output beside it byte for
byte as it was. The outputs are checked before the long work: the work functions are replaced by
ones that fail the test if they are reached.

Full and read-only file systems are real 64 KiB tmpfs mounts (root in a container may mount them);
where mounting is refused those cases are skipped with the reason.
"""
from __future__ import annotations

import io
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from typer.testing import CliRunner

BIN = Path(sys.executable).parent
EARLIER = b"frame,theta\n0,0.25\n"  # an earlier output that must survive every failure byte for byte
ENV = {k: v for k, v in os.environ.items() if k not in ("SYNERGY_PATH", "COLUMNS")}


def _run(args, merged=False, timeout=120):
    return subprocess.run([str(a) for a in args], capture_output=not merged, text=True, timeout=timeout, env=ENV,
                          **({"stdout": subprocess.PIPE, "stderr": subprocess.STDOUT} if merged else {}))


def _ok(args):
    r = _run(args)
    assert r.returncode == 0, r.stderr
    return r


# ----------------------------------------------------------------------------- inputs, made once
@pytest.fixture(scope="module")
def inp(tmp_path_factory):
    """A 3-frame synthetic recording, a tracking output of it (its truth, as a perfect tracker
    would give), its PNGs as a plain folder, and a half-second simulated mocap trial with its true
    angles."""
    from tracker.io.recording import Recording
    from handmodel.dofs import DOF_NAMES
    from tracker.io.tracking_file import write_tracking

    d = tmp_path_factory.mktemp("inputs")
    _ok([BIN / "tracker", "synth", "--frames", "3", "-o", d / "rec"])
    truth = Recording.open(d / "rec").truth
    df = truth[["frame", "time_s"]].assign(status="tracked", fit_mm=1.0, points_used=500, points=900, ms=20.0)
    write_tracking(d / "track.csv", df.join(truth[list(DOF_NAMES)]), {"recording": str(d / "rec")})
    (d / "pngs").mkdir()
    for p in sorted((d / "rec" / "depth").glob("*.png")):
        shutil.copy(p, d / "pngs" / p.name)
    _ok([BIN / "synergy", "simulate", "--motions", "power_grasp", "--trials", "1", "--duration", "0.5",
         "-o", d / "sim"])
    return SimpleNamespace(rec=d / "rec", track=d / "track.csv", pngs=d / "pngs", c3d=d / "sim" / "power_grasp_01.c3d",
                           angles=d / "sim" / "truth" / "power_grasp_01.csv")


# name: (kind of output, suffix of a file output, argv given the inputs, the output and a writable scratch folder)
COMMANDS = {
    "tracker track -o": ("file", ".csv", lambda i, o, s: ["tracker", "track", i.rec, "-o", o]),
    "tracker track --keypoints": ("file", ".csv",
                                  lambda i, o, s: ["tracker", "track", i.rec, "-o", s / "t.csv", "--keypoints", o]),
    "tracker track --overlay": ("folder", "",
                                lambda i, o, s: ["tracker", "track", i.rec, "-o", s / "t.csv", "--overlay", o]),
    "tracker eval --plot": ("file", ".png", lambda i, o, s: ["tracker", "eval", i.rec, i.track, "--plot", o]),
    "tracker import": ("folder", "", lambda i, o, s: ["tracker", "import", i.pngs, "-o", o, "--camera", "kinect1"]),
    "tracker show": ("file", ".png", lambda i, o, s: ["tracker", "show", i.rec, "-o", o]),
    "tracker synth": ("folder", "", lambda i, o, s: ["tracker", "synth", "--frames", "3", "-o", o]),
    "tracker experiments": ("folder", "", lambda i, o, s: ["tracker", "experiments", "--quick", "-o", o]),
    "synergy simulate": ("folder", "", lambda i, o, s: ["synergy", "simulate", "--motions", "power_grasp",
                                                        "--trials", "1", "--duration", "0.5", "-o", o]),
    "synergy calibrate": ("file", ".yaml",
                          lambda i, o, s: ["synergy", "calibrate", i.c3d, "--markers", "hand16", "-o", o]),
    "synergy angles": ("folder", "", lambda i, o, s: ["synergy", "angles", i.c3d, "--markers", "hand16", "-o", o]),
    "synergy fit": ("folder", "", lambda i, o, s: ["synergy", "fit", "--angles", i.angles, "--name", "tiny", "-o", o]),
    "synergy plot": ("folder", "", lambda i, o, s: ["synergy", "plot", "fingerfist", "-o", o]),
}

# Commands whose first output is larger than one 4 KiB page, so on a nearly full disk the write
# itself fails (one of each kind of writer: plot PNG, recording folder, C3D, bundle; CSV and YAML
# go through the same atomic_write_text as the CSVs of test_reliability).
NEARLY_FULL = ["tracker show", "tracker synth", "synergy simulate", "synergy fit"]


def _argv(name, inp, out, scratch):
    _, _, make = COMMANDS[name]
    args = make(inp, out, scratch)
    return [BIN / args[0], *args[1:]]


def _out(where: Path, name: str) -> Path:
    kind, suffix, _ = COMMANDS[name]
    return where / f"out{suffix}"


# ----------------------------------------------------------------------------- file systems
def _mount(where: Path, opts: str) -> bool:
    where.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        return False
    return subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(where)], capture_output=True).returncode == 0


@pytest.fixture
def tiny(tmp_path):
    """A 64 KiB file system holding an earlier output; unmounted afterwards."""
    d = tmp_path / "tiny"
    if not _mount(d, "size=64k"):
        pytest.skip("cannot mount a tmpfs here (not root, or mounting refused)")
    (d / "earlier.csv").write_bytes(EARLIER)
    yield d
    subprocess.run(["umount", "-l", str(d)], check=False)


@pytest.fixture
def ro_fs(tiny):
    """``tiny`` remounted read-only, the earlier output still in it."""
    if subprocess.run(["mount", "-o", "remount,ro", str(tiny)], capture_output=True).returncode != 0:
        pytest.skip("cannot remount a tmpfs read-only here")
    return tiny


def _fill(d: Path, leave_pages: int = 0) -> None:
    """Fill the file system of ``d`` up, then free ``leave_pages`` pages again."""
    with open(d / "filler", "wb", buffering=0) as fh:
        try:
            while True:
                if not fh.write(b"\0" * 4096):
                    break
        except OSError:
            pass
    size = (d / "filler").stat().st_size
    os.truncate(d / "filler", max(size - size % 4096 - 4096 * leave_pages, 0))
    assert os.statvfs(d).f_bavail == leave_pages


@pytest.fixture
def full_fs(tiny):
    _fill(tiny)
    return tiny


@pytest.fixture
def nearly_full_fs(tiny):
    _fill(tiny, leave_pages=1)
    return tiny


def _snapshot(d: Path) -> dict:
    """Every entry under ``d`` (hidden ones too): bytes of files, None for folders."""
    return {str(p.relative_to(d)): (None if p.is_dir() else p.read_bytes()) for p in sorted(d.rglob("*"))}


def _assert_refused(r, out: Path, words: str):
    """Exit 2, nothing on stdout, exactly ``error: <out>: <words>`` on stderr."""
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert "Traceback" not in r.stderr
    assert r.stderr == f"error: {out}: {words}\n", r.stderr
    assert r.stdout == ""


# ----------------------------------------------------------------------------- (a) read-only
@pytest.mark.parametrize("name", COMMANDS)
def test_read_only_output(name, inp, ro_fs, tmp_path):
    out = _out(ro_fs, name)
    before = _snapshot(ro_fs)
    r = _run(_argv(name, inp, out, tmp_path))
    _assert_refused(r, out, "read-only file system")
    assert _snapshot(ro_fs) == before and (ro_fs / "earlier.csv").read_bytes() == EARLIER
    assert not (tmp_path / "t.csv").exists()  # the other output of track was not written either


# ----------------------------------------------------------------------------- (b) folder / file
@pytest.mark.parametrize("name", COMMANDS)
def test_folder_where_a_file_goes_and_file_where_a_folder_goes(name, inp, tmp_path):
    where = tmp_path / "outputs"
    where.mkdir()
    (where / "earlier.csv").write_bytes(EARLIER)
    out = _out(where, name)
    kind = COMMANDS[name][0]
    if kind == "file":
        out.mkdir()
        words = "is a folder, not a file"
    else:
        out.write_bytes(EARLIER)
        words = "exists and is not a folder"
    before = _snapshot(where)
    r = _run(_argv(name, inp, out, tmp_path))
    _assert_refused(r, out, words)
    assert _snapshot(where) == before


def test_folder_where_a_file_inside_the_output_folder_goes(inp, tmp_path):
    """The output folder is fine but a file it gets is a folder: refused before any trial is
    converted, one line naming it."""
    out = tmp_path / "out"
    (out / "power_grasp_01.csv").mkdir(parents=True)
    (out / "earlier.csv").write_bytes(EARLIER)
    before = _snapshot(out)
    r = _run(_argv("synergy angles", inp, out, tmp_path))
    _assert_refused(r, out / "power_grasp_01.csv", "exists and is never overwritten (choose another -o)")
    assert _snapshot(out) == before


# ----------------------------------------------------------------------------- (c) full
@pytest.mark.parametrize("name", COMMANDS)
def test_full_file_system(name, inp, full_fs, tmp_path):
    out = _out(full_fs, name)
    before = _snapshot(full_fs)
    r = _run(_argv(name, inp, out, tmp_path))
    _assert_refused(r, out, "no space left on the device")
    assert _snapshot(full_fs) == before and (full_fs / "earlier.csv").read_bytes() == EARLIER


@pytest.mark.parametrize("name", NEARLY_FULL)
def test_nearly_full_file_system_fails_in_the_write(name, inp, nearly_full_fs, tmp_path):
    """One free page passes the check; the output does not fit. Error last, nothing published."""
    out = _out(nearly_full_fs, name)
    before = _snapshot(nearly_full_fs)
    r = _run(_argv(name, inp, out, tmp_path), merged=True)
    lines = r.stdout.splitlines()
    assert r.returncode == 2 and "Traceback" not in r.stdout, r.stdout
    assert [ln for ln in lines if ln.startswith("error")] == lines[-1:], r.stdout  # one error line, the last
    # ezc3d reports no error on a full disk: its output is refused when it reads back short
    assert re.fullmatch(rf"error: {re.escape(str(out))}\S*: .*(no space left on (the )?device\)?|C3D file reads back as .*)",
                        lines[-1], re.IGNORECASE), lines[-1]
    after = _snapshot(nearly_full_fs)
    assert (nearly_full_fs / "earlier.csv").read_bytes() == EARLIER
    new = {k: v for k, v in after.items() if k not in before}
    # no temporary file is left, and nothing under a final name holds data: at most empty folders
    assert all(v is None for v in new.values()), sorted(new)


# ----------------------------------------------------------------------------- before the long work
def _work_of(name):
    """(module, attribute) of the functions that do a command's long work."""
    return {
        "tracker track -o": [("tracker.run", "track_recording"), ("tracker.io.recording.Recording", "open")],
        "tracker track --keypoints": [("tracker.run", "track_recording"), ("tracker.io.recording.Recording", "open")],
        "tracker track --overlay": [("tracker.run", "track_recording"), ("tracker.io.recording.Recording", "open")],
        "tracker eval --plot": [("tracker.io.recording.Recording", "open"), ("tracker.evaluate", "summarise")],
        "tracker import": [("tracker.io.recording", "import_pngs")],
        "tracker show": [("tracker.io.recording.Recording", "open")],
        "tracker synth": [("tracker.sim.motions", "make_motion"), ("tracker.sim.synthesize", "synthesize")],
        "tracker experiments": [("tracker.sim.report", "report")],
        "synergy simulate": [("synergy.simulate", "motion"), ("synergy.simulate", "simulate_markers")],
        "synergy calibrate": [("synergy.c3d", "read_c3d"), ("synergy.calibrate", "calibrate")],
        "synergy angles": [("synergy.markers", "load_markerset"), ("synergy.c3d", "read_c3d")],
        "synergy fit": [("synergy.fit", "read_trial")],
        "synergy plot": [("synergy.bundle", "load_bundle")],
    }[name]


@pytest.mark.parametrize("name", COMMANDS)
def test_outputs_are_checked_before_the_long_work(name, inp, full_fs, tmp_path, monkeypatch):
    import importlib

    from synergy.cli import app as synergy_app
    from tracker.cli import app as tracker_app

    reached = []
    # every module imported before any is patched: a module imported for the first time while another's
    # function is patched keeps the patch after the test (tracker.sim.synthesize binds
    # tracker.sim.motions.make_motion at its import), and the tests after this one meet it
    owners = []
    for mod, attr in _work_of(name):
        head, _, cls = mod.rpartition(".") if mod.endswith("Recording") else (mod, "", "")
        owner = getattr(importlib.import_module(head), cls) if cls else importlib.import_module(mod)
        owners.append((mod, attr, cls, owner))
    for mod, attr, cls, owner in owners:

        def work(*a, _what=f"{mod}.{attr}", **k):
            reached.append(_what)
            raise AssertionError(f"{_what} ran before the output was checked")

        monkeypatch.setattr(owner, attr, staticmethod(work) if cls else work)
    out = _out(full_fs, name)
    args = [str(a) for a in _argv(name, inp, out, tmp_path)]
    app = tracker_app if args[0].endswith("tracker") else synergy_app
    r = CliRunner().invoke(app, args[1:], env={"SYNERGY_PATH": ""})
    assert reached == [] and r.exit_code == 2, (reached, r.output)
    assert r.stderr == f"error: {out}: no space left on the device\n"


# ----------------------------------------------------------------------------- plain error lines
def test_list_shows_names_and_reasons_as_typed(tmp_path):
    """A registry path with markup-like text and an invalid bundle: printed literally (the old
    code read ``[/b]`` as a closing tag and failed with a traceback)."""
    from synergy.bundle import save_bundle
    from synergy.pca import SynergyModel

    reg = tmp_path / "reg [/b] [red]x"
    reg.mkdir(parents=True)
    rng = np.random.default_rng(0)
    model = SynergyModel(n_components=0.95).fit(rng.normal(size=(200, 3)) @ rng.normal(size=(3, 20)))
    path = save_bundle(model, "grip", registry=reg)
    bad = reg / "grip-1.0.1.npz"
    bad.write_bytes(path.read_bytes()[:-100])  # truncated: an invalid bundle with a reason
    from synergy.cli import app

    r = CliRunner().invoke(app, ["list", "-r", str(reg)], env={"COLUMNS": "1000", "SYNERGY_PATH": ""})
    assert r.exit_code == 0 and r.stderr == "", (r.exception, r.stderr)
    rows = [ln for ln in r.stdout.splitlines() if "grip" in ln]
    assert len(rows) == 2 and all(str(reg) in ln for ln in rows), r.stdout
    assert "invalid: " in rows[1] and "1.0.1" in rows[1]


def test_angles_errors_come_last_and_plainly(inp, tmp_path):
    """One bad trial among good ones: the good ones are converted and summed up, then the error
    line, plain (the name is not read as markup) and last."""
    bad = tmp_path / "trials [/red]" / "bad [bold].c3d"  # "[/red]" would be a closing tag to rich
    bad.parent.mkdir(parents=True)
    bad.write_bytes(b"not a c3d file")
    out = tmp_path / "angles"
    r = _run([BIN / "synergy", "angles", inp.c3d, bad, "--markers", "hand16", "-o", out], merged=True)
    lines = r.stdout.splitlines()
    assert r.returncode == 2 and "Traceback" not in r.stdout, r.stdout
    assert lines[-1].startswith(f"error: {bad}: ") and sum(ln.startswith("error") for ln in lines) == 1, r.stdout
    assert (out / "power_grasp_01.csv").is_file() and not (out / f"{bad.stem}.csv").exists()
    assert any("power_grasp_01.c3d" in ln for ln in lines[:-1])  # the summary came before the error


# ----------------------------------------------------------------------------- bundle manifests
@pytest.mark.parametrize("value", ["NaN", "Infinity", "-Infinity"])
def test_bundle_manifest_with_non_finite_numbers_is_refused(tmp_path, value):
    """``json.loads`` reads NaN and Infinity; a manifest holding one (hash resealed, so only this
    check can catch it) is refused naming the field."""
    from synergy.bundle import manifest_sha256, read_bundle, save_bundle
    from synergy.errors import BundleError
    from synergy.pca import SynergyModel

    rng = np.random.default_rng(1)
    model = SynergyModel(n_components=0.95).fit(rng.normal(size=(200, 3)) @ rng.normal(size=(3, 20)))
    path = save_bundle(model, "grip", registry=tmp_path, heldout={"method": "x", "rms_rad": [0.2, 0.1]})
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    man = json.loads(str(arrays["manifest"][()]))
    man["heldout"]["rms_rad"][1] = float(value.replace("Infinity", "inf"))
    man["manifest_sha256"] = manifest_sha256(man)
    text = json.dumps(man)
    assert value in text
    arrays["manifest"] = np.array(text)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    path.write_bytes(buf.getvalue())
    with pytest.raises(BundleError, match=r"malformed manifest: heldout\.rms_rad\.1: -?(nan|inf) is not a finite number"):
        read_bundle(path)
    # nor is one written
    with pytest.raises(BundleError, match="not a finite number"):
        save_bundle(model, "grip", registry=tmp_path, heldout={"method": "x", "rms_rad": [0.2, float("nan")]})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["grip-1.0.0.npz"]


def test_track_summary_when_no_frame_has_a_hand(inp, tmp_path):
    """A run that segments nothing (a depth range beyond the hand) says so, and shows no tracking rate: a
    lost frame costs nothing, so a median over all frames showed tens of thousands of fps for a run that
    tracked nothing."""
    r = _ok([BIN / "tracker", "track", inp.rec, "-o", tmp_path / "t.csv", "--depth-range", "3,4", "--hand-scale", "1"])
    out = " ".join(r.stdout.split())
    assert "warning: no hand found in any frame" in out, r.stdout
    # what to check names the options given first; no size to reuse from a run that found no hand
    assert "check the --depth-range 3,4 m given, the hand size 1 given" in out, r.stdout
    assert "reuse it with" not in out, r.stdout
    row = next(line for line in r.stdout.splitlines() if re.match(r"^\W*3\W", line))
    cells = [c.strip() for c in re.split(r"[│┃|]", row) if c.strip()]
    assert cells[:3] == ["3", "0", "3"] and cells[5:7] == ["-", "-"], cells
