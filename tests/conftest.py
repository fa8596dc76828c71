import contextlib
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"

#: Set in the child process of an ``isolated`` test, which then runs as any other.
_ISOLATED_CHILD = "SHT_ISOLATED_CHILD"
#: Seconds an isolated test may take before its process is killed and the test fails.
ISOLATED_TIMEOUT_S = 300


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "isolated: run in a process of its own, killed after ISOLATED_TIMEOUT_S (native code that "
                   "may crash or hang: librealsense's threads)")


@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem):
    """An ``isolated`` test runs in a child pytest: a crash or hang in native code fails that test with its
    output instead of taking down the xdist worker (CI once lost a worker to a segfault during a librealsense
    test, and xdist's loadfile scheduler then hung until CI's time ran out)."""
    if pyfuncitem.get_closest_marker("isolated") is None or os.environ.get(_ISOLATED_CHILD):
        return None
    env = dict(os.environ, **{_ISOLATED_CHILD: "1"})
    first = None
    for attempt in range(2):
        with tempfile.TemporaryDirectory(prefix="isolated-") as base:
            # faulthandler prints every thread's stack shortly before the kill: where it hung
            cmd = [sys.executable, "-X", "faulthandler", "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider",
                   "-o", f"faulthandler_timeout={ISOLATED_TIMEOUT_S * 0.9:g}", "--basetemp", str(Path(base) / "t"),
                   pyfuncitem.nodeid]
            try:
                run = subprocess.run(cmd, cwd=pyfuncitem.config.rootpath, env=env, capture_output=True, text=True,
                                     timeout=ISOLATED_TIMEOUT_S)
            except subprocess.TimeoutExpired as exc:
                run = exc
        # killed by a signal (a segfault in librealsense's threads, once in ~1250 tests under load, while the
        # test itself was importing rosbags after pipe.stop()): run once more; a failed assertion, a second
        # crash or a hang fails as before, with the first crash's output too
        if isinstance(run, subprocess.TimeoutExpired) or run.returncode >= 0 or attempt:
            break
        first = f"first run killed by signal {-run.returncode}:\n{_tail(run.stdout + run.stderr, 30)}\n"
    if isinstance(run, subprocess.TimeoutExpired):
        out = "".join(x.decode(errors="replace") if isinstance(x, bytes) else x
                      for x in (run.stdout or "", run.stderr or ""))
        pytest.fail(f"isolated run killed after {ISOLATED_TIMEOUT_S} s\n{_tail(out)}", pytrace=False)
    out = run.stdout + run.stderr
    if run.returncode == 0 and " passed" not in out.splitlines()[-1]:
        reasons = [ln.split(": ", 1)[-1] for ln in out.splitlines() if ln.startswith("SKIPPED")]
        pytest.skip(reasons[0] if reasons else "skipped in its isolated run")
    if run.returncode != 0:
        pytest.fail(f"{first or ''}isolated run ended with exit code {run.returncode}\n{_tail(out)}", pytrace=False)
    if first:
        import warnings

        warnings.warn(f"{pyfuncitem.nodeid}: {first.splitlines()[0]}; passed on its second run", stacklevel=1)
    return True


def _tail(text: str, lines: int = 80) -> str:
    return "\n".join(text.splitlines()[-lines:])


def shared(*parts) -> Path:
    """A file under ../shared/data, or skip the test with the reason."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"third-party test data not available: {p} (../shared/data is absent)")
    return p


def import_pyrealsense2():
    """pyrealsense2, or skip the test with the reason and the install line: the extra is missing, or its
    wheel is there but the system libusb is not (an ImportError, not a ModuleNotFoundError)."""
    try:
        import pyrealsense2
    except ImportError as exc:
        pytest.skip(f"pyrealsense2 cannot be imported ({exc}): pip install 'synergistic-hand-tracking[realsense]' "
                    "and the system libusb (Debian: apt-get install libusb-1.0-0)", allow_module_level=True)
    return pyrealsense2


@contextlib.contextmanager
def played_by_librealsense(rs, bag, attempts: int = 3):
    """Every frame of a ``.bag`` as librealsense plays it: ``({stream: [frame, …]}, depth scale in m)``,
    valid inside the ``with`` (the device's extrinsics go when it is unloaded).

    The file is played by its sensors, not a pipeline: a pipeline plays in real time until
    ``set_real_time(False)`` takes effect, and a loaded machine loses frames that way (CI once got no
    frameset with both streams three times in a row), whereas a device set to non-real-time before its
    sensors start delivers every frame (each once here, in file order). Even so, CI once got a play
    of the D435 file without its one colour frame (the playback stopped, the frame never came); a play
    that misses a stream is played again from a freshly loaded device, up to ``attempts`` times.
    """
    import time

    for attempt in range(attempts):
        ctx = rs.context()
        dev = ctx.load_device(str(bag))
        playback = dev.as_playback()
        playback.set_real_time(False)
        scale = dev.first_depth_sensor().get_depth_scale()
        frames = {}

        def keep(f, frames=frames):
            got = frames.setdefault(f.get_profile().stream_type(), [])
            # a device reads its file again when a second sensor starts after the first (seen under load)
            if all(g.get_timestamp() != f.get_timestamp() for g in got):
                f.keep()
                got.append(f)

        sensors = dev.query_sensors()
        try:
            for s in sensors:
                s.open(s.get_stream_profiles()[0])
                s.start(keep)
            deadline, stopped_since = time.monotonic() + 10, None
            while time.monotonic() < deadline:
                if playback.current_status() == rs.playback_status.stopped:
                    stopped_since = stopped_since or time.monotonic()
                    if len(frames) == len(sensors) or time.monotonic() - stopped_since > 1:
                        break
                else:
                    stopped_since = None
                time.sleep(0.05)
            time.sleep(0.2)  # a frame in flight when the status changed
            for s in sensors:
                s.stop()
            if len(frames) == len(sensors) or attempt == attempts - 1:
                if attempt:
                    import warnings

                    warnings.warn(f"{Path(bag).name}: librealsense's play {attempt + 1} had every stream", stacklevel=3)
                yield {k: sorted(v, key=lambda f: f.get_timestamp()) for k, v in frames.items()}, scale
                return
        finally:
            for s in sensors:
                try:
                    s.stop()
                except RuntimeError:  # stopped already
                    pass
                s.close()
            ctx.unload_device(str(bag))


@pytest.fixture(scope="session")
def hand():
    from handmodel import HandModel

    return HandModel.load()


@pytest.fixture(scope="session")
def fingerfist():
    """The 6000×26 fingerfist postures (global translation in mm as in the file)."""
    return np.loadtxt(shared("htrack_schroeder", "fingerfist.txt"))


def realistic_frame(hand, sensor, scale, spec, frame, noise_seed=0, seed=0, motion="open-close", frames=30):
    """``(camera, depth, colour, labels)``: frame ``frame`` of a realistic scene as
    :func:`tracker.sim.experiments.run_scene` renders it — ``motion`` (``frames`` frames, motion ``seed``), the
    model ``hand`` × ``scale`` with :func:`~tracker.sim.experiments.realistic_fingers` (``seed``),
    ``spec``'s clutter sized with it and placed from the motion's mean hand centre, ``sensor``'s camera
    and noise (seeded ``[noise_seed, frame]``; ``experiment_realistic(seed=s)``'s scene ``j`` is
    ``seed=s, noise_seed=s + j``)."""
    from tracker.io.cameras import preset
    from tracker.sim import experiments as E
    from tracker.sim.hands import HandShape
    from tracker.sim.motions import make_motion
    from tracker.sim.noise import NoiseModel
    from tracker.sim.render import DepthRenderer

    cam_name, noise_name = E.REALISTIC_SENSORS[sensor]
    cam, nm = preset(cam_name), NoiseModel.preset(noise_name)
    shown = HandShape(scale, E.realistic_fingers(scale, seed)).apply(hand)
    truth = make_motion(motion, hand=shown, frames=frames, seed=seed).theta
    clutter = E.placed_clutter(spec, hand, shown, truth)
    r = DepthRenderer(shown, cam).render(truth[frame], labels=True, color=True, clutter=clutter,
                                         incidence=nm.needs_incidence, reflectance=nm.needs_reflectance)
    depth = nm.apply(r.depth, cam, np.random.default_rng([noise_seed, frame]), r.cos_incidence, r.reflectance)
    return cam, depth, r.color, r.labels


def harder_frame(motion, sensor, scale, frame, noise_seed=2, frames=45):
    """``(hand, camera, depth, colour, labels, true keypoints)``: frame ``frame`` of the harder scenes' ``motion``
    as ``tools/harder_scenes.py`` renders it (forearm and torso, the tracking hand × ``scale`` with
    :func:`~tracker.sim.experiments.realistic_fingers`, noise seed 2 by default), the keypoints of the hand shown."""
    from handmodel import HandModel
    from tracker import TRACKING_HAND
    from tracker.sim.experiments import realistic_fingers
    from tracker.sim.hands import HandShape
    from tracker.sim.motions import make_motion

    hand = HandModel.load(TRACKING_HAND)
    cam, depth, color, labels = realistic_frame(hand, sensor, scale, "forearm,torso", frame, noise_seed=noise_seed,
                                                motion=motion, frames=frames)
    shown = HandShape(scale, realistic_fingers(scale, 0)).apply(hand)
    kp = shown.keypoints(make_motion(motion, hand=shown, frames=frames, seed=0).theta[frame])
    return hand, cam, depth, color, labels, kp


def mask_scores(mask, depth, labels):
    """``(recall, precision)`` of a hand ``mask`` against the rendered hand's seen pixels (``labels`` ≥ 0
    with depth)."""
    seen = (labels >= 0) & np.isfinite(depth)
    both = (mask & seen).sum()
    return both / seen.sum(), both / max(mask.sum(), 1)
