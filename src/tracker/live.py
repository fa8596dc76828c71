"""Live input: frames from a RealSense camera, or a recorded ``.bag`` played back by librealsense,
as a recording-like source for :func:`tracker.run.track_recording` (``tracker live``).

A :class:`RealSenseSource` has what the tracking loop reads from a recording (``camera``,
``fps``, ``handedness``, iteration over :class:`tracker.io.recording.Frame` objects with depth in
metres, NaN for no data), so a camera runs through the same code as ``tracker track``; a ``.bag``
played back by librealsense is how this path is tested without a camera. Playback is not real time:
every recorded frame is delivered, in order, however slow the tracker (:class:`_Playback`).

Intrinsics and the depth scale come from the device (or the file); lens distortion is ignored
(RealSense depth streams report none). Colour, when asked for, is aligned to the depth image (by
librealsense for a camera, by :func:`tracker.io.images.register_color` for a playback), so it serves skin
segmentation as a recording's ``color/`` frames do.

Needs the optional extra ``realsense`` (pyrealsense2, which needs the system libusb); without it a
:class:`RealSenseSource` is a :class:`tracker.errors.TrackerError` naming what to install.
"""
from __future__ import annotations

import queue
import threading
import time
from pathlib import Path

import numpy as np

from .io.cameras import Camera
from .errors import TrackerError
from .io.images import register_color, units_to_metres
from .io.recording import Frame

try:  # an optional extra: RealSenseSource names what to install when it is missing
    import pyrealsense2 as rs
except ImportError as exc:
    rs, _MISSING = None, str(exc)


def _require():
    if rs is None:
        if "libusb" in _MISSING:
            raise TrackerError("pyrealsense2", "needs the system libusb (e.g. apt install libusb-1.0-0)")
        raise TrackerError("pyrealsense2", "live cameras need pyrealsense2 "
                                           "(pip install 'synergistic-hand-tracking[realsense]')")


def _one_line(exc) -> str:
    """librealsense's message of ``exc`` on one line (its messages can hold line breaks)."""
    return " ".join(str(exc).split())


#: Seconds without a frame after which a camera counts as stalled (playback: as finished).
TIMEOUT_S = 5.0


#: Frames (depth; colour) a playback may read ahead of the tracker (librealsense waits while they wait).
_AHEAD = 8
#: Seconds a finished playback is still waited on for frames on their way to the callbacks (they pass
#: librealsense's dispatcher threads, which a loaded machine holds back: at 0.3 s CI saw a frame's colour
#: missing, and with 8 busy processes on 2 cores 3 of 30 playbacks of the D435 file did; at 1 s, 0 of 30).
#: Paid once, at the end of a file.
_END_GRACE_S = 1.0


_RGB_FORMATS = () if rs is None else (rs.format.rgb8, rs.format.bgr8, rs.format.rgba8, rs.format.bgra8)


class _Playback:
    """Every frame of a ``.bag``, in order, through librealsense's playback device.

    Not through a pipeline: a pipeline starts its playback in real time and keeps one frameset, so
    frames read before ``set_real_time(False)`` took effect were lost when the process stalled for
    one frame period (seen under CI load: 4 of 5 frames). Here real time is off before the sensor
    starts, and the depth callback waits for room in a bounded queue, which holds the file's reader.

    Colour (optional) is read by a second playback device of the same file: a device starts reading at
    its first sensor's start, so a second sensor started after it misses what was read before (the
    D435 file's one colour frame, under load: then the device read the file again when the second
    sensor started). It is the recorded frame nearest in time, registered onto the depth image with
    the file's depth→colour extrinsics by :class:`RealSenseSource`; its reader waits while
    ``_AHEAD`` colour frames lie ahead of the depth frames taken.
    """

    def __init__(self, path: Path, color: bool):
        self.path = path
        self._depth = queue.Queue(maxsize=_AHEAD)
        self._colors = []  # (stamp_s, rgb) in time order, pruned as depth frames take theirs
        self._lock = threading.Condition()
        self._closing = False
        self._failure = None
        self._sensors = []
        self.color_fmt = None
        self._cpb = None
        try:
            self._dev = rs.context().load_device(str(path))
            self._pb = self._dev.as_playback()
            self._pb.set_real_time(False)
            found = self._profile(self._dev, rs.stream.depth)
            if found is None:
                raise RuntimeError("no depth stream in the file")
            self.depth_profile, depth_sensor = found
            self.scale = float(depth_sensor.as_depth_sensor().get_depth_scale())
            starts = [(depth_sensor, self.depth_profile, self._on_depth)]
            found = self._profile(self._dev, rs.stream.color) if color else None
            # colour in another format (YUYV, raw) is left out, as frames of the wrong shape were before
            if found is not None and found[0].format() in _RGB_FORMATS:
                cprof = found[0]
                self.color_fmt = cprof.format()
                k = cprof.as_video_stream_profile().get_intrinsics()
                self.color_K = np.array([[k.fx, 0, k.ppx], [0, k.fy, k.ppy], [0, 0, 1.0]])
                ex = self.depth_profile.get_extrinsics_to(cprof)
                self.color_R = np.asarray(ex.rotation, float).reshape(3, 3).T  # librealsense: column-major
                self.color_t = np.asarray(ex.translation, float)
                cdev = rs.context().load_device(str(path))
                self._cpb = cdev.as_playback()
                self._cpb.set_real_time(False)
                cprof2, csensor = self._profile(cdev, rs.stream.color)
                self._cdev = cdev  # held while its sensor streams
                starts.append((csensor, cprof2, self._on_color))
            for sensor, prof, callback in starts:
                sensor.open(prof)
                self._sensors.append(sensor)
                sensor.start(callback)
        except RuntimeError as exc:
            self.close()
            raise TrackerError(path, f"librealsense cannot start the stream ({_one_line(exc)})") from None

    @staticmethod
    def _profile(dev, stream):
        for sensor in dev.query_sensors():
            for prof in sensor.get_stream_profiles():
                if prof.stream_type() == stream:
                    return prof, sensor
        return None

    def _on_depth(self, f) -> None:
        try:
            item = (f.get_timestamp() / 1000.0, np.asanyarray(f.get_data()).copy())
        except Exception as exc:  # noqa: BLE001 - librealsense's thread: next() raises it
            self._failure = self._failure or exc
            return
        while not self._closing:
            try:
                self._depth.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def _on_color(self, f) -> None:
        try:
            rgb = np.asanyarray(f.get_data())
            if self.color_fmt in (rs.format.bgr8, rs.format.bgra8):
                rgb = rgb[..., 2::-1]
            item = (f.get_timestamp() / 1000.0, np.ascontiguousarray(rgb[..., :3]))
        except Exception as exc:  # noqa: BLE001 - librealsense's thread: next() raises it
            self._failure = self._failure or exc
            return
        with self._lock:
            # the colour reader runs at most _AHEAD frames ahead of the depth frames taken
            while len(self._colors) >= _AHEAD and not self._closing:
                self._lock.wait(0.1)
            self._colors.append(item)
            self._lock.notify_all()

    @staticmethod
    def _stopped(pb) -> bool:
        return pb.current_status() == rs.playback_status.stopped

    def next(self, timeout_s: float):
        """``(stamp_s, depth units, rgb or None)`` of the next depth frame; None at the end."""
        waited, step, stopped_for = 0.0, 0.05, 0.0
        while True:
            if self._failure is not None:
                raise TrackerError(self.path, f"unreadable frame ({_one_line(self._failure)})")
            try:
                stamp, units = self._depth.get(timeout=step)
                break
            except queue.Empty:
                waited += step
            # the end: stopped, and nothing came while frames could still be on their way
            stopped_for = stopped_for + step if self._stopped(self._pb) else 0.0
            if stopped_for >= _END_GRACE_S or waited >= timeout_s:
                return None
        return stamp, units, (self._color_at(stamp) if self._cpb is not None else None)

    def _color_at(self, stamp):
        """The colour frame nearest ``stamp``, once one at or after it has come (or the colour ended)."""
        t0 = time.monotonic()
        stopped_since = None
        with self._lock:
            while True:
                # frames before the last one at or before stamp are nearer to no later depth frame
                while len(self._colors) > 1 and self._colors[1][0] <= stamp:
                    del self._colors[0]
                self._lock.notify_all()
                now = time.monotonic()
                if self._stopped(self._cpb):
                    stopped_since = now if stopped_since is None else stopped_since
                else:
                    stopped_since = None
                done = (any(t >= stamp for t, _ in self._colors) or now - t0 >= TIMEOUT_S
                        or (stopped_since is not None and now - stopped_since >= _END_GRACE_S))
                if done:
                    if not self._colors:
                        return None
                    return min(self._colors, key=lambda c: abs(c[0] - stamp))[1]
                self._lock.wait(0.05)

    def close(self) -> None:
        self._closing = True  # a callback waiting for room gives up
        for sensor in self._sensors:
            for call in (sensor.stop, sensor.close):
                try:
                    call()
                except RuntimeError:
                    pass  # already stopped at the end of the file
        self._sensors = []
        # the devices go here, in the caller's thread once their sensors stopped, not whenever the garbage
        # collector next runs in whatever code comes after (CI once crashed in a later command's start-up)
        self._pb = self._cpb = self._dev = self._cdev = None


class RealSenseSource:
    """Depth (and optionally aligned colour) frames from a RealSense camera or a ``.bag`` file.

    Parameters
    ----------
    playback : a ``.bag`` recorded by RealSense Viewer / librealsense to play back instead of a camera
    serial : the camera's serial number (default: the first camera found)
    width, height, fps : the depth stream to ask a camera for (playback: as recorded)
    color : also take the colour stream, aligned to the depth image
    max_frames, max_seconds : stop after this many frames / seconds of stream time (None: no limit)
    handedness : the hand in front of the camera, ``left`` or ``right``
    timeout_s : seconds to wait for a frame

    Attributes
    ----------
    camera : :class:`tracker.io.cameras.Camera` of the depth stream (device intrinsics and depth scale)
    fps, handedness, name : the stream's rate, the hand, the device (or file) name
    frames_ : frames delivered so far
    """

    def __init__(self, playback=None, *, serial=None, width=640, height=480, fps=30, color=False, max_frames=None,
                 max_seconds=None, handedness="left", timeout_s=TIMEOUT_S):
        _require()
        self.playback = None if playback is None else Path(playback)
        self.handedness = handedness
        self.max_frames = max_frames
        self.max_seconds = max_seconds
        self.timeout_s = float(timeout_s)
        self.frames_ = 0
        self._stop = False
        self._color = bool(color)
        self._reader = self._pipe = self._align = None
        self._t0 = None
        if self.playback is not None:
            if not self.playback.is_file():
                raise TrackerError(self.playback, "no such file to play back")
            self._reader = _Playback(self.playback, color)
            try:
                self._describe(self._reader.depth_profile.as_video_stream_profile(), self._reader.scale,
                               self.playback.name)
            except RuntimeError as exc:
                self.close()
                raise TrackerError(self.playback, f"unusable depth stream ({_one_line(exc)})") from None
            return
        if len(rs.context().query_devices()) == 0:
            raise TrackerError("camera", "no RealSense camera connected (connect one, or play a recording "
                                         "back with --playback FILE.bag)")
        cfg = rs.config()
        if serial:
            cfg.enable_device(str(serial))
        cfg.enable_stream(rs.stream.depth, int(width), int(height), rs.format.z16, int(fps))
        if color:
            cfg.enable_stream(rs.stream.color, int(width), int(height), rs.format.rgb8, int(fps))
        self._pipe = rs.pipeline()
        try:
            profile = self._pipe.start(cfg)
        except RuntimeError as exc:
            raise TrackerError("camera", f"librealsense cannot start the stream ({_one_line(exc)})") from None
        try:
            dev = profile.get_device()
            self._describe(profile.get_stream(rs.stream.depth).as_video_stream_profile(),
                           float(dev.first_depth_sensor().get_depth_scale()),
                           f"{dev.get_info(rs.camera_info.name)} {dev.get_info(rs.camera_info.serial_number)}")
            self._align = rs.align(rs.stream.depth) if color else None
        except RuntimeError as exc:
            self.close()
            raise TrackerError("camera", f"unusable depth stream ({_one_line(exc)})") from None

    def _describe(self, vp, scale: float, name: str) -> None:
        k = vp.get_intrinsics()
        self.name = name
        self.fps = float(vp.fps())
        self.camera = Camera(int(k.width), int(k.height), float(k.fx), float(k.fy), float(k.ppx), float(k.ppy),
                             scale, "uint16", f"realsense {name}")

    def stop(self) -> None:
        """End the iteration after the frame in hand (safe to call from a signal handler)."""
        self._stop = True

    def _limit_reached(self, t) -> bool:
        return (self._stop or (self.max_frames is not None and self.frames_ >= self.max_frames)
                or (self.max_seconds is not None and t is not None and t >= self.max_seconds))

    def _next(self):
        """``(stamp_s, depth units, colour or None)`` of the next frame, or None at the end of a playback."""
        if self._reader is not None:
            return self._reader.next(self.timeout_s)
        # a camera: librealsense's pipeline keeps the newest frameset, which is what live tracking wants
        waited, step = 0.0, 0.1
        while True:
            ok, fs = self._pipe.try_wait_for_frames(int(step * 1000))
            if ok:
                if self._align is not None:
                    fs = self._align.process(fs)
                d = fs.get_depth_frame()
                if d:
                    break
            waited += step
            if waited >= self.timeout_s:
                raise TrackerError("camera", f"no frame from {self.name} for {self.timeout_s:g} s")
        color = None
        if self._color:
            c = fs.get_color_frame()
            color = np.asanyarray(c.get_data()).copy() if c else None
        return d.get_timestamp() / 1000.0, np.asanyarray(d.get_data()).copy(), color

    def __iter__(self):
        while not self._limit_reached(None):
            item = self._next()
            if item is None:
                return
            stamp, units, color = item
            if self._t0 is None:
                self._t0 = stamp
            t = stamp - self._t0
            if self._limit_reached(t):
                return
            depth = units_to_metres(units, self.camera)
            if color is not None and self._reader is not None:
                r = self._reader
                color = register_color(depth, self.camera, color, r.color_K, r.color_R, r.color_t)
            if color is not None and color.shape != self.camera.shape + (3,):
                color = None
            frame = Frame(self.frames_, t, depth, color)
            self.frames_ += 1
            yield frame

    def close(self) -> None:
        """Stop the stream (idempotent)."""
        reader, self._reader = getattr(self, "_reader", None), None
        if reader is not None:
            reader.close()
        pipe, self._pipe = getattr(self, "_pipe", None), None
        if pipe is not None:
            try:
                pipe.stop()
            except RuntimeError:
                pass  # never started, or already stopped by the end of a playback

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __repr__(self) -> str:
        return f"RealSenseSource({self.name!r}, {self.camera.width}×{self.camera.height}, {self.fps:g} fps)"
