"""Writing a recording folder frame by frame (:class:`RecordingWriter`; the layout is
:mod:`tracker.io.folder`'s)."""
from __future__ import annotations

import shutil
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from handmodel.dofs import DOF_NAMES
from handmodel.fileio import atomic_write_bytes, atomic_write_text

from ..errors import RecordingError
from .base import _OWN, FPS_RANGE, HANDEDNESS, SCHEMA_VERSION, check_frame_size
from .cameras import MAX_UNITS, as_camera
from .images import encode_units, metres_to_units, png_bytes


class RecordingWriter:
    """Write a recording folder frame by frame; use as a context manager.

    Each PNG is written atomically (temporary file + rename); ``truth.csv`` and then
    ``recording.yaml`` are written at :meth:`close`, so a folder without ``recording.yaml`` is an
    unfinished recording. An existing non-empty folder is refused unless ``overwrite=True``, which
    replaces a previous recording (and refuses a folder holding anything else). An error inside the
    ``with`` block (a damaged input frame) removes what was written (:meth:`abort`): a failed import
    leaves no half recording that the next attempt would have to ``--overwrite``.

    Parameters
    ----------
    path : folder to create
    camera : Camera (intrinsics, size, depth encoding and scale)
    fps : frame rate (Hz)
    handedness : ``left`` or ``right``
    overwrite : replace an existing recording in ``path``
    source : free text stored in ``recording.yaml`` (where the frames came from)
    """

    def __init__(self, path, camera, fps: float = 30.0, handedness: str = "left", *, overwrite: bool = False,
                 source: str = ""):
        self.path = Path(path)
        if handedness not in HANDEDNESS:
            raise RecordingError(self.path, f"handedness must be left or right, got {handedness!r}")
        try:
            fps = float(fps)
        except (TypeError, ValueError):
            raise RecordingError(self.path, f"fps must be a number, got {fps!r}") from None
        if not (np.isfinite(fps) and FPS_RANGE[0] <= fps <= FPS_RANGE[1]):
            raise RecordingError(self.path, f"fps must be between {FPS_RANGE[0]:g} and {FPS_RANGE[1]:g} Hz, got {fps}")
        self.camera = as_camera(camera)
        check_frame_size(self.camera.width, self.camera.height, self.path)
        self.fps = fps
        self.handedness = handedness
        self.source = str(source)
        self.n = 0
        self.truth: list[np.ndarray] = []
        self.color: bool | None = None
        self._closed = False
        self._created = not self.path.exists()
        self._written: list[Path] = []
        self._prepare(overwrite)

    def _prepare(self, overwrite: bool):
        p = self.path
        if p.exists() and not p.is_dir():
            raise RecordingError(p, "exists and is not a folder")
        entries = list(p.iterdir()) if p.exists() else []
        if not entries:
            return
        if not overwrite:
            raise RecordingError(p, "exists and is not empty (never overwritten; use another folder, or --overwrite)")
        leftover = {e.name for e in entries if e.name.startswith(".") and e.name.endswith(".tmp")}  # a crashed write
        alien = sorted(e.name for e in entries if e.name not in _OWN | leftover)
        if alien:
            raise RecordingError(p, f"holds {', '.join(alien[:3])}, not part of a recording; refusing to overwrite")
        # recording.yaml goes first: a half-cleared folder must not look like a recording
        for e in sorted(entries, key=lambda e: e.name != "recording.yaml"):
            shutil.rmtree(e) if e.is_dir() and not e.is_symlink() else e.unlink()

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def abort(self) -> None:
        """Remove the frames written so far (and the folder, when this writer made it); the writer is
        closed. Nothing else in the folder is touched."""
        if self._closed:
            return
        self._closed = True
        for f in self._written:
            f.unlink(missing_ok=True)
        for d in (self.path / "depth", self.path / "color", *((self.path,) if self._created else ())):
            try:
                d.rmdir()  # only when empty
            except OSError:
                pass

    def __len__(self) -> int:
        return self.n

    def write(self, depth_m, color=None, truth=None) -> int:
        """Append a frame: depth ``(H, W)`` in metres (NaN/0 = no data), optional colour ``(H, W, 3)``
        uint8 and θ ``(26,)``. Returns the frame index."""
        where = self.path / "depth" / f"{self.n:06d}.png"
        return self._write(metres_to_units(depth_m, self.camera, where), color, truth)

    def write_units(self, units, color=None, truth=None) -> int:
        """Append a frame given as stored depth units ``(H, W)`` (integers 0…65535, 0 = no data)."""
        where = self.path / "depth" / f"{self.n:06d}.png"
        u = np.asarray(units)
        if u.shape != self.camera.shape:
            raise RecordingError(where, f"depth frame is {u.shape}, the camera says {self.camera.shape}")
        if not np.issubdtype(u.dtype, np.integer) or (u.size and (u.min() < 0 or u.max() > MAX_UNITS)):
            raise RecordingError(where, f"depth units must be integers in 0…{MAX_UNITS}")
        return self._write(u.astype(np.uint16), color, truth)

    def _write(self, units, color, truth) -> int:
        if self._closed:
            raise RecordingError(self.path, "writer is closed")
        name = f"{self.n:06d}.png"
        has_color = color is not None
        if self.color is not None and has_color != self.color:
            raise RecordingError(self.path / "color" / name, "colour must be given for all frames or none")
        if has_color:
            c = np.asarray(color)
            if c.shape != self.camera.shape + (3,) or c.dtype != np.uint8:
                raise RecordingError(self.path / "color" / name,
                                     f"colour frame must be {self.camera.height}×{self.camera.width}×3 uint8, "
                                     f"got {c.dtype} {c.shape}")
        if (truth is not None) != bool(self.truth) and self.n > 0:
            raise RecordingError(self.path / "truth.csv", f"frame {self.n}: truth must be given for all frames or none")
        if truth is not None:
            t = np.asarray(truth, float)
            if t.shape != (len(list(DOF_NAMES)),):
                raise RecordingError(self.path / "truth.csv", f"frame {self.n}: truth must have shape "
                                                              f"({len(list(DOF_NAMES))},), got {t.shape}")
        self._written.append(atomic_write_bytes(self.path / "depth" / name, png_bytes(encode_units(units, self.camera))))
        if has_color:
            self._written.append(atomic_write_bytes(self.path / "color" / name, png_bytes(c)))
        if truth is not None:
            self.truth.append(t.copy())
        self.color = has_color
        self.n += 1
        return self.n - 1

    def close(self):
        """Write ``truth.csv`` (if any) and ``recording.yaml``."""
        import yaml

        if self._closed:
            return
        self.path.mkdir(parents=True, exist_ok=True)
        if self.truth:
            names = list(DOF_NAMES)
            # repr() is the shortest text that reads back to the same float
            lines = [",".join(["frame", "time_s", *names])]
            lines += [",".join([str(i), repr(i / self.fps), *map(repr, map(float, t))])
                      for i, t in enumerate(self.truth)]
            atomic_write_text(self.path / "truth.csv", "\n".join(lines) + "\n", overwrite=True)
        cam = self.camera
        meta = {
            "schema_version": SCHEMA_VERSION,
            "camera": {"name": cam.name, "width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy,
                       "cx": cam.cx, "cy": cam.cy},
            "depth": {"encoding": cam.depth_encoding, "scale_m": cam.depth_scale_m},
            "fps": self.fps, "handedness": self.handedness, "frames": self.n,
            "color": bool(self.color), "truth": bool(self.truth),
            "created": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "generator": "synergistic-hand-tracking", "source": self.source,
        }
        atomic_write_text(self.path / "recording.yaml", yaml.safe_dump(meta, sort_keys=False), overwrite=True)
        self._closed = True

