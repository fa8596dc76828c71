"""Start-up (issue 39): what a tracking process loads, and what the ``tracker`` program leaves to its end.

Each check runs in a fresh interpreter: what one test imported would hide another's import.
"""
import os
import subprocess
import sys


def _python(code: str) -> str:
    """The last line ``code`` prints in a fresh interpreter."""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout.strip().splitlines()[-1]


def test_tracking_modules_load_no_detector_or_plots():
    # a run without a detector or overlays needs neither the keypoint fit (and its forests) nor
    # matplotlib: each is loaded by the function that uses it (sizing's detector seed, run's overlays)
    heavy = ("tracker.keypoint_fit", "tracker.detector", "matplotlib", "tracker.plots")
    out = _python("import sys, types, tracker.run, tracker.track, tracker.sizing\n"
                  # a size calibration without a detector seed asks for none of them either
                  "tr = types.SimpleNamespace(search=types.SimpleNamespace(keypoints=None))\n"
                  "extra = tracker.sizing.SizeCalibration._detected(None, tr, None)\n"
                  f"print(extra, [m for m in {heavy!r} if m in sys.modules])")
    assert out == "{} []", out


def test_the_program_freezes_its_objects_for_the_exit_but_the_app_does_not():
    # tracker's entry (main, through run_command) skips the exit's collection of every object (~0.4 s);
    # the typer app run inside a process that goes on (a test, a notebook) must keep collecting its garbage
    code = ("import gc, sys\n"
            "from typer.testing import CliRunner\n"
            "from tracker.cli import app, run_command\n"
            "r = CliRunner().invoke(app, ['--help'])\n"
            "assert r.exit_code == 0, r.output\n"
            "after_app = gc.get_freeze_count()\n"
            "sys.argv = ['tracker', '--help']\n"
            "try:\n"
            "    run_command()\n"
            "except SystemExit as e:\n"
            "    assert not e.code, e.code\n"
            "print(after_app, gc.get_freeze_count() > 0)")
    assert _python(code) == "0 True"


def test_the_program_ends_with_its_command_status_after_the_exit_work_that_matters(tmp_path):
    # main ends the process without the interpreter's teardown (~0.07 s of a one-still track), but first
    # joins the other threads, runs every atexit callback (those registered before it too: a coverage
    # collector, temporary folders) and flushes Python's and the C library's buffered output
    done = tmp_path / "thread.txt"
    code = ("import atexit, ctypes, sys, threading, time\n"
            "print('before', end=' ')\n"  # buffered: stdout is a pipe
            "ctypes.CDLL(None).printf(b'c-stdio ')\n"  # the C library's buffer, not Python's
            "atexit.register(lambda: print('atexit-first-registered'))\n"
            f"threading.Thread(target=lambda: (time.sleep(0.3), open({str(done)!r}, 'w').write('done'))).start()\n"
            # the C library's exit handlers run at the interpreter's exit only, which main skips: this one
            # would end the process with SIGABRT
            "libc = ctypes.CDLL(None)\n"
            "libc.__cxa_atexit(ctypes.cast(libc.abort, ctypes.c_void_p), None, None)\n"
            "from tracker.cli import main\n"
            "sys.argv = ['tracker'] + sys.argv[1:]\n"
            "main()\n"
            "print('not reached')\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}  # output buffered, as a user's is

    def no_core_file():
        import resource

        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))

    for args, status in ((["--help"], 0), (["track", str(tmp_path / "none"), "-o", str(tmp_path / "o.csv")], 2)):
        done.unlink(missing_ok=True)
        r = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=300, env=env,
                           cwd=tmp_path, preexec_fn=no_core_file)
        assert r.returncode == status, r.stderr[-2000:]
        assert r.stdout.startswith("before "), r.stdout[:200]
        # the C library's buffer comes out apart from Python's (after it, when both are flushed at the end)
        assert "c-stdio" in r.stdout, r.stdout[-300:]
        assert r.stdout.replace("c-stdio ", "").rstrip().endswith("atexit-first-registered"), r.stdout[-300:]
        assert ("Usage: tracker" in r.stdout) == (status == 0), r.stdout[:300]
        assert ("no such recording folder" in r.stderr) == (status == 2), r.stderr[-300:]
        assert done.read_text() == "done"  # the thread finished before the process ended
        assert "not reached" not in r.stdout, r.stdout[-300:]


def test_the_program_leaves_a_status_that_is_no_number_to_the_interpreter():
    # sys.exit("message") prints the message and exits 1: main leaves it to the interpreter's own exit
    code = ("import sys, tracker.cli as cli\n"
            "def app():\n"
            "    raise SystemExit('a message')\n"
            "cli.app = app\n"
            "cli.main()\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert (r.returncode, r.stderr) == (1, "a message\n")


def test_start_up_pauses_the_collector_and_gives_it_back_as_it_was():
    # in a process that goes on (program False) nothing is frozen; a collector that was off stays off
    code = ("import gc\n"
            "from tracker.cli_common import StartUp\n"
            "seen = []\n"
            "with StartUp() as s:\n"
            "    seen.append(gc.isenabled())\n"
            "    s.done()\n"
            "    seen.append(gc.isenabled())\n"
            "    s.done()\n"
            "seen.append(gc.isenabled())\n"
            "gc.disable()\n"
            "with StartUp() as s:\n"
            "    s.done()\n"
            "seen.append(gc.isenabled())\n"
            "gc.enable()\n"
            "try:\n"
            "    with StartUp():\n"
            "        raise KeyError\n"
            "except KeyError:\n"
            "    seen.append(gc.isenabled())\n"
            "print(seen, gc.get_freeze_count())")
    assert _python(code) == "[False, True, True, False, True] 0"
    # in the tracker program the start-up's objects are frozen when it is done
    code = ("import gc\n"
            "from tracker.cli_common import StartUp\n"
            "StartUp.program = True\n"
            "with StartUp() as s:\n"
            "    x = [[] for _ in range(1000)]\n"
            "    s.done()\n"
            "print(gc.isenabled(), gc.get_freeze_count() >= 1000)")
    assert _python(code) == "True True"


def test_a_failed_track_or_calibrate_in_a_process_that_goes_on_leaves_the_collector_on(tmp_path):
    # each command fails after its start-up began (no such recording): the collector is on again,
    # nothing frozen (a notebook or test process keeps collecting its garbage)
    none = str(tmp_path / "none")
    for args in (["track", none, "-o", str(tmp_path / "o.csv")], ["calibrate", none, "-o", str(tmp_path / "h.yaml")]):
        code = ("import gc\n"
                "from typer.testing import CliRunner\n"
                "from tracker.cli import app\n"
                f"r = CliRunner().invoke(app, {args!r})\n"
                "print(r.exit_code, 'no such recording' in r.output, gc.isenabled(), gc.get_freeze_count())")
        assert _python(code) == "2 True True 0", args


def test_tracking_one_recording_loads_no_pandas_and_writes_what_pandas_would(tmp_path):
    # tracker track of one recording writes its outputs from the run's FrameTable without pandas (~0.2 s
    # of its start-up): the files are the ones pandas writes of the same table, a lost frame included
    import numpy as np

    from tracker.io.images import png_bytes
    from tracker.io.tracking_file import read_tracking
    from tracker.sim.synthesize import synthesize

    rec = tmp_path / "rec"
    synthesize("open-close", "kinect1", None, rec, frames=3)
    (rec / "depth" / "000001.png").write_bytes(png_bytes(np.zeros((480, 640), np.uint16)))  # no hand: lost
    out, kp = tmp_path / "t.csv", tmp_path / "k.csv"
    code = ("import sys\n"
            "import tracker.run\n"
            "runs, real = [], tracker.run.run_job\n"
            "tracker.run.run_job = lambda *a, **k: runs.append(real(*a, **k)) or runs[-1]\n"
            "from tracker.cli import run_command\n"
            f"sys.argv = ['tracker', 'track', {str(rec)!r}, '-o', {str(out)!r}, '--keypoints', {str(kp)!r},\n"
            "            '--hand-scale', '1', '--no-check-hand']\n"
            "try:\n"
            "    run_command()\n"
            "except SystemExit as e:\n"
            "    assert not e.code, e.code\n"
            "loaded = [m for m in ('pandas', 'pyarrow') if m in sys.modules]\n"
            "from tracker.io.tracking_file import keypoints_table, tracking_csv\n"
            "run = runs[0]\n"
            "kp_text = ''.join(f'# {k}: {run.meta[k]}\\n' for k in ('recording', 'handedness'))\n"
            "kp_text += keypoints_table(run.tracker.hand, run.df).to_csv(index=False, float_format='%.4f')\n"
            f"same = (open({str(out)!r}).read() == tracking_csv(run.df, run.meta), open({str(kp)!r}).read() == kp_text)\n"
            "print(loaded, same)")
    assert _python(code) == "[] (True, True)"
    df, _ = read_tracking(out)
    assert df["status"].tolist()[1] == "lost" and df["status"].tolist()[0] != "lost"


def test_a_missing_recording_fails_before_the_tracker_loads(tmp_path):
    # the one-line error of a mistyped recording path comes before the tracker's modules (numba, the
    # kernels: ~1 s) load, in tracker track, info and show; the same error as opening it gives
    pngs = tmp_path / "pngs"
    pngs.mkdir()
    (pngs / "0001.png").write_bytes(b"")
    cases = [(tmp_path / "none.bag", f"error: {tmp_path / 'none.bag'}: no such recording file"),
             (tmp_path / "none", f"error: {tmp_path / 'none'}: no such recording folder"),
             (pngs, f"error: {pngs / 'recording.yaml'}: missing: {pngs} holds 1 PNG files, not a recording; import "
                    f"them first: tracker import {pngs} --camera PRESET --hand left|right -o RECORDING")]
    commands = (["track", "-o", str(tmp_path / "o.csv")], ["info"], ["show", "-o", str(tmp_path / "o.png")],
                ["calibrate", "-o", str(tmp_path / "hand.yaml")])
    for (path, line), (name, *options) in zip(cases * len(commands), [c for c in commands for _ in cases]):
        code = ("import sys\n"
                "from typer.testing import CliRunner\n"
                "from tracker.cli import app\n"
                f"r = CliRunner().invoke(app, [{name!r}, {str(path)!r}, *{options!r}])\n"
                "heavy = [m for m in ('numba', 'scipy', 'numpy', 'matplotlib', 'tracker.segment', 'tracker.run')\n"
                "         if m in sys.modules]\n"
                "print(repr((r.exit_code, r.stderr, heavy)))")
        assert _python(code) == repr((2, line + "\n", [])), (name, path)
        # the recording's own reader says the same
        from tracker.errors import RecordingError
        from tracker.io.recording import Recording

        try:
            Recording.open(path)
        except RecordingError as exc:
            assert f"error: {exc}" == line
        else:
            raise AssertionError(f"{path} opened")
    assert not (tmp_path / "o.csv").exists() and not (tmp_path / "o.png").exists()
    assert not (tmp_path / "hand.yaml").exists()


def test_a_missing_playback_fails_before_the_tracker_loads(tmp_path):
    # tracker live --playback: the same line RealSenseSource gives, before numba, the kernels and pyrealsense2
    bag = tmp_path / "none.bag"
    code = ("import sys\n"
            "from typer.testing import CliRunner\n"
            "from tracker.cli import app\n"
            f"r = CliRunner().invoke(app, ['live', '--playback', {str(bag)!r}, '-o', {str(tmp_path / 'o.csv')!r}])\n"
            "heavy = [m for m in ('numba', 'numpy', 'pyrealsense2', 'tracker.segment', 'tracker.run')\n"
            "         if m in sys.modules]\n"
            "print(repr((r.exit_code, r.stderr, heavy)))")
    assert _python(code) == repr((2, f"error: {bag}: no such file to play back\n", []))
    assert not (tmp_path / "o.csv").exists()
