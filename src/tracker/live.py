"""Live input: frames from a RealSense camera, or a recorded ``.bag`` played back by librealsense,
as a recording-like source for :func:`tracker.run.track_recording` (``tracker live``).

A :class:`RealSenseSource` has what the tracking loop reads from a recording (``camera``,
``fps``, ``handedness``, iteration over :class:`tracker.recording.Frame` objects with depth in
metres, NaN for no data), so a camera runs through the same code as ``tracker track``; a ``.bag``
played back through the same librealsense pipeline is how this path is tested without a camera.
Playback is not real time: every recorded frame is delivered, however slow the tracker.

Intrinsics and the depth scale come from the device (or the file); lens distortion is ignored
(RealSense depth streams report none). Colour, when asked for, is aligned to the depth image by
librealsense, so it serves skin segmentation as a recording's ``color/`` frames do.

Needs the optional extra ``realsense`` (pyrealsense2, which needs the system libusb); without it a
:class:`RealSenseSource` is a :class:`tracker.errors.TrackerError` naming what to install.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .cameras import Camera
from .errors import TrackerError
from .images import units_to_metres
from .recording import Frame

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


#: Seconds without a frame after which a camera counts as stalled (playback: as finished).
TIMEOUT_S = 5.0


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
    camera : :class:`tracker.cameras.Camera` of the depth stream (device intrinsics and depth scale)
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
        where = self.playback if self.playback is not None else "camera"
        cfg = rs.config()
        if self.playback is not None:
            if not self.playback.is_file():
                raise TrackerError(self.playback, "no such file to play back")
            cfg.enable_device_from_file(str(self.playback), repeat_playback=False)
            # the file's own streams: depth, and colour if asked for (the syncer would drop depth
            # frames waiting for colour partners the file does not hold)
            cfg.enable_stream(rs.stream.depth)
            if color:
                cfg.enable_stream(rs.stream.color)
        else:
            devices = rs.context().query_devices()
            if len(devices) == 0:
                raise TrackerError("camera", "no RealSense camera connected (connect one, or play a recording "
                                             "back with --playback FILE.bag)")
            if serial:
                cfg.enable_device(str(serial))
            cfg.enable_stream(rs.stream.depth, int(width), int(height), rs.format.z16, int(fps))
            if color:
                cfg.enable_stream(rs.stream.color, int(width), int(height), rs.format.rgb8, int(fps))
        self._pipe = rs.pipeline()
        try:
            profile = self._pipe.start(cfg)
        except RuntimeError as exc:
            raise TrackerError(where, f"librealsense cannot start the stream ({' '.join(str(exc).split())})") from None
        try:
            dev = profile.get_device()
            self._playback = None
            if self.playback is not None:
                self._playback = dev.as_playback()
                self._playback.set_real_time(False)  # every frame, however slow the tracker
            self.name = (self.playback.name if self.playback is not None
                         else f"{dev.get_info(rs.camera_info.name)} {dev.get_info(rs.camera_info.serial_number)}")
            scale = float(dev.first_depth_sensor().get_depth_scale())
            vp = profile.get_stream(rs.stream.depth).as_video_stream_profile()
            k = vp.get_intrinsics()
            self.fps = float(vp.fps())
            self.camera = Camera(int(k.width), int(k.height), float(k.fx), float(k.fy), float(k.ppx), float(k.ppy),
                                 scale, "uint16", f"realsense {self.name}")
            self._align = rs.align(rs.stream.depth) if color else None
        except (RuntimeError, TrackerError) as exc:
            self.close()
            raise TrackerError(where, f"unusable depth stream ({' '.join(str(exc).split())})") from None
        self._t0 = None

    def stop(self) -> None:
        """End the iteration after the frame in hand (safe to call from a signal handler)."""
        self._stop = True

    def _limit_reached(self, t) -> bool:
        return (self._stop or (self.max_frames is not None and self.frames_ >= self.max_frames)
                or (self.max_seconds is not None and t is not None and t >= self.max_seconds))

    def _next(self):
        """The next frameset, or None at the end of a playback."""
        # short waits, so the end of a file is seen at once and not after the whole timeout
        waited, step = 0.0, 0.1
        while True:
            ok, fs = self._pipe.try_wait_for_frames(int(step * 1000))
            if ok:
                return fs
            if self._playback is not None and self._playback.current_status() == rs.playback_status.stopped:
                return None
            waited += step
            if waited >= self.timeout_s:
                if self._playback is not None:
                    return None
                raise TrackerError("camera", f"no frame from {self.name} for {self.timeout_s:g} s")

    def __iter__(self):
        while not self._limit_reached(None):
            fs = self._next()
            if fs is None:
                return
            if self._align is not None:
                fs = self._align.process(fs)
            d = fs.get_depth_frame()
            if not d:
                continue
            stamp = d.get_timestamp() / 1000.0
            if self._t0 is None:
                self._t0 = stamp
            t = stamp - self._t0
            if self._limit_reached(t):
                return
            units = np.asanyarray(d.get_data()).copy()
            depth = units_to_metres(units, self.camera)
            color = None
            if self._color:
                c = fs.get_color_frame()
                color = np.asanyarray(c.get_data()).copy() if c else None
                if color is not None and color.shape != self.camera.shape + (3,):
                    color = None
            frame = Frame(self.frames_, t, depth, color)
            self.frames_ += 1
            yield frame

    def close(self) -> None:
        """Stop the stream (idempotent)."""
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
