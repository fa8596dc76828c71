"""The base of the readers of recording files (:mod:`tracker.io.bags`, :mod:`tracker.io.mkv`): a
file read in place behind the :class:`~tracker.io.folder.Recording` interface. The readers import
this module, never the dispatcher (:mod:`tracker.io.files`) that imports them.
"""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np

from ..errors import RecordingError
from .base import FPS_RANGE, Frame
from .cameras import Camera
from .folder import Recording
from .images import metres_to_units, units_to_metres


class FileRecording(Recording):
    """A recording file read in place, behind the :class:`Recording` interface.

    Subclasses (:class:`tracker.io.bags.BagRecording`, :class:`tracker.io.mkv.MkvRecording`) index the
    depth frames of the file once (``stamps_ns``, the file's own timestamps) and decode a frame on
    demand in :meth:`_read_raw`. ``Frame.time_s`` is the file's time of the frame, counted from the
    file's first depth frame; ``fps`` is the stream's nominal rate (or, without one, the median
    frame interval). :meth:`select` cuts a time span or thins the frames without reading them.
    """

    #: what :meth:`_read_raw` gives: integer ``units`` (× camera.depth_scale_m) or float ``metres``
    depth_kind = "units"
    #: what is wrong with a file whose frames still read up to the damage (say "cut short: …"), or ""
    #: for a sound one: the commands warn of it, as the frames past it are missing
    damage = ""

    def __init__(self, path, camera: Camera, stamps_ns, fps: float, handedness: str, source: str,
                 has_color: bool):
        self.path = Path(path)
        self.camera = camera
        self.fps = float(fps)
        if not (np.isfinite(self.fps) and FPS_RANGE[0] <= self.fps <= FPS_RANGE[1]):
            raise RecordingError(self.path, f"a frame rate of {self.fps:g} Hz is not a camera's (damaged frame rate "
                                            "or time stamps?)")
        self.handedness = handedness
        self.truth = None
        self._theta = None
        self._color = True if has_color else None
        self._stamps = np.asarray(stamps_ns, np.int64)
        self._sel = np.arange(len(self._stamps))
        self.source = source
        self.meta = {"camera": {"name": camera.name, "width": camera.width, "height": camera.height,
                                "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy},
                     "depth": {"encoding": camera.depth_encoding, "scale_m": camera.depth_scale_m},
                     "fps": self.fps, "handedness": handedness, "frames": len(self._stamps),
                     "color": bool(has_color), "truth": False, "source": source}

    def __len__(self) -> int:
        return len(self._sel)

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({str(self.path)!r}, {len(self)} frames, {self.camera.width}×"
                f"{self.camera.height}, {self.fps:g} fps, {self.handedness})")

    @property
    def times_s(self) -> np.ndarray:
        """The file's time of each selected frame (s from the file's first depth frame)."""
        return (self._stamps[self._sel] - (self._stamps[0] if len(self._stamps) else 0)) / 1e9

    def select(self, start_s: float | None = None, end_s: float | None = None, every: int = 1) -> "FileRecording":
        """The frames from ``start_s`` up to and including ``end_s`` (seconds of the file's time, as
        :attr:`times_s` counts), every ``every``-th of them; a new view, nothing is read."""
        if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
            raise RecordingError(self.path, f"--every must be a positive integer, got {every!r}")
        for name, v in (("--start", start_s), ("--end", end_s)):
            if v is not None and not np.isfinite(v):
                raise RecordingError(self.path, f"{name} must be a finite number of seconds, got {v!r}")
            if v is not None and v < 0:
                # the file's time starts at 0 (its first depth frame): a negative time is a typo, not "from the start"
                raise RecordingError(self.path, f"{name} must be ≥ 0 s (seconds from the first depth frame), got {v:g}")
        t = self.times_s
        keep = np.ones(len(t), bool)
        if start_s is not None:
            keep &= t >= start_s - 1e-9
        if end_s is not None:
            keep &= t <= end_s + 1e-9
        view = copy.copy(self)
        view._sel = self._sel[keep][::int(every)]
        if not len(view._sel) and len(self._sel):
            span = (f"from {start_s:g} s" if end_s is None else f"up to {end_s:g} s" if start_s is None
                    else f"between {start_s:g} s and {end_s:g} s")
            raise RecordingError(self.path, f"no frames {span} (the file's frames span {t[0]:g}–{t[-1]:g} s)")
        return view

    def _read_raw(self, k: int):
        """Depth of the file's ``k``-th depth frame (``units`` uint16 or ``metres`` float32, as
        :attr:`depth_kind` says) and its registered colour ``(H, W, 3)`` uint8 or None."""
        raise NotImplementedError(f"{type(self).__name__} must read its frames")

    def _depth_metres(self, raw) -> np.ndarray:
        if self.depth_kind == "units":
            return units_to_metres(raw, self.camera)
        d = np.asarray(raw, np.float32).copy()
        d[~(np.isfinite(d) & (d > 0))] = np.nan
        return d

    def __getitem__(self, i) -> Frame:
        i = self._index(i)
        raw, color = self._read_raw(int(self._sel[i]))
        return Frame(i, float(self.times_s[i]), self._depth_metres(raw), color, None)

    def depth_units(self, i: int) -> np.ndarray:
        """Depth units of frame ``i`` (uint16) in the camera's scale: as stored for integer depth,
        rounded to the nearest unit for float (metre) depth."""
        i = self._index(i)
        raw, _ = self._read_raw(int(self._sel[i]))
        if self.depth_kind == "units":
            return raw
        return metres_to_units(self._depth_metres(raw), self.camera, self.path)

    def frame_with_units(self, i: int):
        """``(Frame, units)`` of frame ``i`` from one decode (for conversion to a folder)."""
        i = self._index(i)
        raw, color = self._read_raw(int(self._sel[i]))
        depth = self._depth_metres(raw)
        units = raw if self.depth_kind == "units" else metres_to_units(depth, self.camera, self.path)
        return Frame(i, float(self.times_s[i]), depth, color, None), units

