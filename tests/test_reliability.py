"""Reliability: writes verified before they are published, every OS error one plain line (exit 2),
bounded work on hostile input. Full and read-only file systems are real tiny tmpfs mounts where
the machine allows (root in a container usually does); otherwise the errors are injected."""
import errno
import io
import os
import subprocess
import sys
import time
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest

from handmodel import fileio
from handmodel.cliutil import error_line, errors_exit_2
from handmodel.errors import ToolkitError
from synergy.c3d import read_c3d
from synergy.c3d_write import write_c3d
from synergy.errors import BundleError, TaskMapError
from synergy.tasks import load_task_map
from tracker.errors import RecordingError
from tracker.io.recording import Recording, RecordingWriter

BIN = Path(sys.executable).parent


# ----------------------------------------------------------------------------- file systems
def _mount(where: Path, opts: str) -> bool:
    where.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(where)], capture_output=True)
    return r.returncode == 0


@pytest.fixture
def full_fs(tmp_path):
    """A 64 KiB file system that already holds one earlier output."""
    d = tmp_path / "tiny"
    if os.geteuid() != 0 or not _mount(d, "size=64k"):
        pytest.skip("cannot mount a tmpfs here (the ENOSPC injection tests still run)")
    (d / "earlier.csv").write_text("earlier output\n")
    yield d
    subprocess.run(["umount", "-l", str(d)], check=False)


@pytest.fixture
def ro_fs(tmp_path):
    d = tmp_path / "ro"
    if os.geteuid() != 0 or not _mount(d, "size=64k,ro"):
        pytest.skip("cannot mount a read-only tmpfs here (the EROFS injection tests still run)")
    yield d
    subprocess.run(["umount", "-l", str(d)], check=False)


def _final_files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.rglob("*") if p.is_file())


# ----------------------------------------------------------------------------- verified writes
def test_full_disk_leaves_no_file_and_earlier_outputs_intact(full_fs):
    with pytest.raises(OSError) as e:
        fileio.atomic_write_bytes(full_fs / "big.png", b"x" * (200 << 10))
    assert e.value.errno == errno.ENOSPC and e.value.filename == str(full_fs / "big.png")
    assert _final_files(full_fs) == ["earlier.csv"]            # no temporary file either
    assert (full_fs / "earlier.csv").read_text() == "earlier output\n"
    assert error_line(e.value) == f"error: {full_fs / 'big.png'}: no space left on the device"


def test_full_disk_c3d_is_never_published(full_fs):
    pts = np.random.default_rng(0).normal(size=(2000, 16, 3))
    with pytest.raises(OSError) as e:
        write_c3d(full_fs / "trial.c3d", pts, [f"m{i}" for i in range(16)], 100.0)
    assert e.value.filename == str(full_fs / "trial.c3d")
    assert _final_files(full_fs) == ["earlier.csv"]


def test_silently_truncating_c3d_writer_is_caught(tmp_path, monkeypatch):
    """ezc3d does not report a failed write: a truncated file must not reach its final name."""
    import ezc3d

    real = ezc3d.c3d.write

    def short_write(self, name):
        real(self, name)
        with open(name, "r+b") as fh:
            fh.truncate(16384)

    monkeypatch.setattr(ezc3d.c3d, "write", short_write)
    out = tmp_path / "trial.c3d"
    pts = np.random.default_rng(0).normal(size=(2000, 16, 3))
    with pytest.raises(OSError, match="does not read back|reads back as") as e:
        write_c3d(out, pts, [f"m{i}" for i in range(16)], 100.0)
    assert e.value.errno == errno.EIO and e.value.filename == str(out)
    assert os.listdir(tmp_path) == []
    monkeypatch.undo()
    write_c3d(out, pts, [f"m{i}" for i in range(16)], 100.0)
    assert read_c3d(out).n_frames == 2000


class _FailingFile(io.BytesIO):
    def __init__(self, err):
        super().__init__()
        self.err = err

    def write(self, b):
        raise OSError(self.err, os.strerror(self.err))


@pytest.mark.parametrize("err", [errno.ENOSPC, errno.EDQUOT, errno.EIO])
def test_injected_write_errors_name_the_output(tmp_path, monkeypatch, err):
    (tmp_path / "earlier.csv").write_text("kept")
    real_open = open

    def fake_open(f, mode="r", *a, **k):
        if "w" in mode:
            real_open(f, mode, *a, **k).close()
            return _FailingFile(err)
        return real_open(f, mode, *a, **k)

    monkeypatch.setattr(fileio, "open", fake_open, raising=False)
    with pytest.raises(OSError) as e:
        fileio.atomic_write_text(tmp_path / "out.csv", "a,b\n")
    assert e.value.errno == err and e.value.filename == str(tmp_path / "out.csv")
    assert sorted(os.listdir(tmp_path)) == ["earlier.csv"]
    assert (tmp_path / "earlier.csv").read_text() == "kept"


def test_short_write_is_refused(tmp_path, monkeypatch):
    real_open = open

    class Short(io.FileIO):
        def write(self, b):
            return super().write(bytes(b)[: len(b) // 2])

    def fake_open(f, mode="r", *a, **k):
        return Short(f, "w") if "w" in mode else real_open(f, mode, *a, **k)

    monkeypatch.setattr(fileio, "open", fake_open, raising=False)
    with pytest.raises(OSError, match="differs"):
        fileio.atomic_write_bytes(tmp_path / "x.bin", b"0123456789")
    assert os.listdir(tmp_path) == []


def test_output_that_is_a_folder(tmp_path):
    (tmp_path / "out.csv").mkdir()
    with pytest.raises(IsADirectoryError) as e:
        fileio.atomic_write_text(tmp_path / "out.csv", "a\n")
    assert error_line(e.value) == f"error: {tmp_path / 'out.csv'}: is a folder, not a file"
    with pytest.raises(IsADirectoryError):
        fileio.check_output(tmp_path / "out.csv")


def test_check_output_before_long_work(tmp_path, ro_fs):
    with pytest.raises(OSError) as e:
        fileio.check_output(ro_fs / "sub" / "x.csv")
    assert e.value.errno == errno.EROFS and e.value.filename == str(ro_fs / "sub" / "x.csv")
    (tmp_path / "file").write_text("")
    with pytest.raises(NotADirectoryError):
        fileio.check_output(tmp_path / "file" / "x.csv")
    with pytest.raises(NotADirectoryError):
        fileio.check_output(tmp_path / "file", folder=True)
    with pytest.raises(FileExistsError):
        fileio.check_output(tmp_path / "file")
    assert fileio.check_output(tmp_path / "new" / "x.csv") == tmp_path / "new" / "x.csv"
    assert sorted(os.listdir(tmp_path)) == ["file", "ro"]    # the probe left nothing behind


def test_corrupt_npz_output_is_refused(tmp_path):
    with pytest.raises(OSError, match="archive"):
        fileio.atomic_write_bytes(tmp_path / "b.npz", b"PK\x03\x04 not really a zip")
    assert os.listdir(tmp_path) == []


# ----------------------------------------------------------------------------- error lines
@pytest.mark.parametrize("err, words", [
    (errno.ENOSPC, "no space left on the device"), (errno.EROFS, "read-only file system"),
    (errno.EACCES, "permission denied"), (errno.EISDIR, "is a folder, not a file"),
    (errno.ENOTDIR, "a part of the path is not a folder")])
def test_os_errors_are_one_line_naming_the_path(err, words):
    e = OSError(err, os.strerror(err), "/data/out [bold]x[/bold].csv")
    assert error_line(e) == f"error: /data/out [bold]x[/bold].csv: {words}"


def test_wrapper_prints_plainly_and_exits_2(capsys):
    import typer

    long_name = "/tmp/" + "a" * 300 + "/[bold]name[/bold].csv"

    @errors_exit_2
    def cmd():
        raise OSError(errno.EROFS, "Read-only file system", long_name)

    with pytest.raises(typer.Exit) as e:
        cmd()
    assert e.value.exit_code == 2
    err = capsys.readouterr().err
    assert err == f"error: {long_name}: read-only file system\n"   # one line, markup kept

    @errors_exit_2
    def bad():
        raise ToolkitError("f.yaml", "two\nlines")

    with pytest.raises(typer.Exit):
        bad()
    assert capsys.readouterr().err == "error: f.yaml: two lines\n"


def _run(args, timeout=60, **kw):
    return subprocess.run(args, capture_output=True, text=True, timeout=timeout, **kw)


def _run_measured(args, tmp_path, timeout=60):
    """Run a command; ``(returncode, stderr, peak RSS in bytes, CPU seconds)`` of that process alone.

    A child forked from pytest starts with pytest's own peak RSS (the kernel keeps the high-water mark
    across exec), so a small launcher process forks the command and reports its ``ru_maxrss``."""
    launcher = ("import os, resource, sys\n"
                "pid = os.fork()\n"
                "if pid == 0:\n"
                "    os.execv(sys.argv[2], sys.argv[2:])\n"
                "_, status, ru = os.wait4(pid, 0)\n"
                "open(sys.argv[1], 'w').write(f'{ru.ru_maxrss} {ru.ru_utime + ru.ru_stime}')\n"
                "sys.exit(os.waitstatus_to_exitcode(status))\n")
    rss_path = tmp_path / "maxrss.txt"
    r = subprocess.run([sys.executable, "-c", launcher, str(rss_path), *map(str, args)], capture_output=True,
                       text=True, timeout=timeout)
    rss, cpu = rss_path.read_text().split()
    return r.returncode, r.stderr, int(rss) << 10, float(cpu)


def test_cli_read_only_and_folder_outputs(tmp_path, ro_fs):
    """tracker import and synergy simulate: exit 2, one line naming the output, nothing left."""
    from tracker.io.cameras import preset

    src = tmp_path / "pngs"
    with RecordingWriter(tmp_path / "rec", preset("kinect1")) as w:
        w.write(np.full((480, 640), 0.7, np.float32))
    src.mkdir()
    (src / "a.png").write_bytes((tmp_path / "rec" / "depth" / "000000.png").read_bytes())
    r = _run([BIN / "tracker", "import", str(src), "-o", str(ro_fs / "rec"), "--camera", "kinect1"])
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.count("\n") == 1 and str(ro_fs / "rec") in r.stderr and "read-only" in r.stderr
    r = _run([BIN / "synergy", "simulate", "-o", str(ro_fs / "sim"), "--motions", "power_grasp", "--trials", "1",
              "--duration", "0.5"])
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "read-only" in r.stderr, r.stderr
    assert _final_files(ro_fs) == []
    sheet = tmp_path / "sheet.png"
    sheet.mkdir()                                           # the output is a folder
    r = _run([BIN / "tracker", "show", str(tmp_path / "rec"), "-o", str(sheet), "--overwrite"])
    assert r.returncode == 2 and r.stderr == f"error: {sheet}: is a folder, not a file\n"
    assert r.stdout == ""


# ----------------------------------------------------------------------------- hostile inputs
def _bounded(fn, seconds=5.0):
    t0 = time.monotonic()
    fn()
    assert time.monotonic() - t0 < seconds


BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{c}: &{c} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}]\n" for p, c in zip("abcdefgh", "bcdefghi"))


def test_yaml_alias_bomb_is_refused_at_once(tmp_path):
    assert len(BOMB) < 400
    p = tmp_path / "tasks.yaml"
    p.write_text(BOMB)

    def go():
        with pytest.raises(TaskMapError, match="aliases"):
            load_task_map(p)
        with pytest.raises(RecordingError, match="aliases"):
            fileio.load_yaml(p, RecordingError)

    _bounded(go, 1.0)


def _recording(tmp_path, **meta_changes) -> Path:
    from tracker.io.cameras import preset

    d = tmp_path / "rec"
    with RecordingWriter(d, preset("kinect1"), fps=30) as w:
        w.write(np.full((480, 640), 0.7, np.float32))
    y = d / "recording.yaml"
    text = y.read_text()
    for k, v in meta_changes.items():
        lines = [ln for ln in text.splitlines() if not ln.startswith(f"{k}:")]
        text = "\n".join(lines) + f"\n{k}: {v}\n"
    y.write_text(text)
    return d


def test_huge_frame_count_is_checked_against_the_files_first(tmp_path):
    d = _recording(tmp_path, frames=1000000000)

    def go():
        with pytest.raises(RecordingError, match=r"000001\.png.*\(999999999 missing\)"):
            Recording.open(d)

    _bounded(go, 2.0)


def test_nan_fps_is_refused(tmp_path):
    with pytest.raises(RecordingError, match="fps: nan is not a number"):
        Recording.open(_recording(tmp_path, fps=".nan"))


def test_infinite_fps_is_refused(tmp_path):
    with pytest.raises(RecordingError, match="fps"):
        Recording.open(_recording(tmp_path, fps=".inf"))


def test_non_utf8_recording_yaml(tmp_path):
    d = _recording(tmp_path)
    (d / "recording.yaml").write_bytes(b"source: \xff\xfe caf\xe9\n")
    with pytest.raises(RecordingError, match=r"not UTF-8 text \(byte 0xff at offset 8\)"):
        Recording.open(d)


def test_oversized_frames_are_refused_before_decoding(tmp_path):
    d = _recording(tmp_path)
    y = d / "recording.yaml"
    y.write_text(y.read_text().replace("width: 640", "width: 8000").replace("height: 480", "height: 8000"))
    with pytest.raises(RecordingError, match="maximum|larger than the supported"):
        Recording.open(d)
    from tracker.io.cameras import Camera

    with pytest.raises(RecordingError, match="larger than the supported 4096"):
        RecordingWriter(tmp_path / "big", Camera(8000, 8000, 500.0, 500.0, 4000.0, 4000.0))


def _zip_bomb(path: Path, declared: int) -> Path:
    """A .npz whose one member unpacks to ``declared`` bytes of zeros (a few MB on disk)."""
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False,
                                                  "shape": (declared // 8,)})
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("big.npy", "w", force_zip64=True) as fh:
            fh.write(header.getvalue())
            block = bytes(1 << 20)
            for _ in range(declared // len(block)):
                fh.write(block)
    return path


def test_npz_bomb_is_refused_from_its_declared_sizes(tmp_path):
    p = _zip_bomb(tmp_path / "grip-1.0.0.npz", 1 << 30)
    assert p.stat().st_size < 3 << 20

    def go():
        with pytest.raises(BundleError, match="over the limit"):
            fileio.load_npz(p, BundleError, max_bytes=256 << 20)

    # tracemalloc sees numpy's and Python's allocations: the peak of this call alone (the process's
    # own peak RSS may already be above anything this call could add)
    tracemalloc.start()
    try:
        _bounded(go, 2.0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 100 << 20, peak


def test_misnamed_and_pickled_npz(tmp_path):
    npy = tmp_path / "grip-1.0.0.npz"
    np.save(tmp_path / "x.npy", np.zeros(3))
    (tmp_path / "x.npy").rename(npy)
    with pytest.raises(BundleError, match=r"not a readable \.npz archive \(the file is a \.npy array\)"):
        fileio.load_npz(npy, BundleError)
    pk = tmp_path / "pickle.npz"
    np.savez(pk, a=np.array([{"x": 1}], dtype=object))
    with pytest.raises(BundleError, match="pickles"):
        fileio.load_npz(pk, BundleError)
    ok = tmp_path / "ok.npz"
    np.savez(ok, a=np.arange(4.0), b=np.eye(2))
    with fileio.load_npz(ok, BundleError) as z:
        assert z.files == ["a", "b"] and np.array_equal(z["b"], np.eye(2))


def test_hostile_inputs_through_the_cli_stay_small(tmp_path):
    """tracker info on frames: 10⁹ and synergy angles with an alias-bomb marker set: a clean
    error in under 5 s of CPU and under 500 MB (CPU time, not wall-clock: a shared machine's load
    must not fail it, a loop over the claimed frames still would)."""
    d = _recording(tmp_path, frames=1000000000)
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(BOMB)
    for args in ([BIN / "tracker", "info", str(d)],
                 [BIN / "synergy", "angles", str(tmp_path / "none.c3d"), "--markers", str(bomb), "-o",
                  str(tmp_path / "out")]):
        code, err, rss, cpu = _run_measured(args, tmp_path)
        assert cpu < 5, (args[1], cpu)
        assert code == 2 and err.startswith("error: ") and err.count("\n") == 1, err
        assert rss < 500 << 20, (args[1], rss >> 20)


@pytest.mark.parametrize("cls", [ToolkitError, BundleError, RecordingError])
def test_errors_cross_process_boundaries_as_themselves(cls):
    # a worker's error (Dask, the report's parallel steps) is pickled back to the caller; rebuilt from
    # its formatted message alone it failed to unpickle and broke the whole process pool
    import pickle

    e = pickle.loads(pickle.dumps(cls("rec/frame_0001.png", "not a 16-bit PNG")))
    assert type(e) is cls and e.where == "rec/frame_0001.png" and e.reason == "not a 16-bit PNG"
    assert str(e) == "rec/frame_0001.png: not a 16-bit PNG"
    assert pickle.loads(pickle.dumps(cls(None, "no file"))).where is None
