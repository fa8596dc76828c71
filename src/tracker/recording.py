"""Recording folders (DESIGN.md): ``recording.yaml``, ``depth/000000.png`` …, optional ``color/`` and
``truth.csv``. Frames are read lazily; depth comes out in metres as float32 with NaN for no data.

Examples
--------
>>> import numpy as np, tempfile, pathlib
>>> from tracker.cameras import preset
>>> d = pathlib.Path(tempfile.mkdtemp()) / "rec"
>>> with RecordingWriter(d, preset("kinect1"), fps=30) as w:
...     _ = w.write(np.full((480, 640), 0.75, np.float32))
>>> rec = Recording.open(d); len(rec), float(rec[0].depth[0, 0])
(1, 0.75)
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from handmodel.fileio import atomic_write_bytes, atomic_write_text, load_yaml, schema_errors

from .cameras import Camera
from .errors import RecordingError

DOF_COLUMNS = None  # filled lazily from the default hand model


def _dof_names():
    global DOF_COLUMNS
    if DOF_COLUMNS is None:
        from handmodel import HandModel

        DOF_COLUMNS = HandModel.load().dof_names
    return DOF_COLUMNS


def _natural_key(p: Path):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", p.name)]


@dataclass
class Frame:
    index: int
    time_s: float
    depth: np.ndarray
    color: np.ndarray | None = None
    truth: np.ndarray | None = None


def decode_depth(img, camera: Camera, where="depth") -> np.ndarray:
    """Stored image → metres (float32, NaN = no data), checking the bit depth and the size."""
    a = np.asarray(img)
    if a.shape[:2] != (camera.height, camera.width):
        raise RecordingError(where, f"image is {a.shape[1]}×{a.shape[0]}, the camera says {camera.width}×{camera.height}")
    if camera.depth_encoding == "nyu_rgb":
        if a.ndim != 3 or a.shape[2] < 3 or a.dtype != np.uint8:
            raise RecordingError(where, f"NYU depth needs an 8-bit RGB PNG, got {a.dtype} with shape {a.shape}")
        raw = a[..., 1].astype(np.uint32) * 256 + a[..., 2].astype(np.uint32)
    else:
        if a.ndim != 2:
            raise RecordingError(where, f"depth must be a single-channel image, got shape {a.shape}")
        if a.dtype != np.uint16:
            raise RecordingError(where, f"wrong bit depth: {a.dtype} (16-bit PNG expected)")
        raw = a
    d = raw.astype(np.float32) * np.float32(camera.depth_scale)
    d[raw == 0] = np.nan
    return d


def encode_depth(depth_m, camera: Camera) -> np.ndarray:
    d = np.asarray(depth_m, float)
    if d.shape != (camera.height, camera.width):
        raise RecordingError("depth", f"frame is {d.shape[::-1]}, the camera says {camera.width}×{camera.height}")
    units = np.where(np.isfinite(d) & (d > 0), np.rint(d / camera.depth_scale), 0)
    units = np.clip(units, 0, 65535 if camera.depth_encoding == "uint16" else 65535).astype(np.uint16)
    if camera.depth_encoding == "nyu_rgb":
        rgb = np.zeros(d.shape + (3,), np.uint8)
        rgb[..., 1] = units >> 8
        rgb[..., 2] = units & 255
        return rgb
    return units


def _png_bytes(a) -> bytes:
    import imageio.v3 as iio

    return iio.imwrite("<bytes>", a, extension=".png")


def _read_png(path: Path):
    import imageio.v3 as iio

    try:
        return iio.imread(path)
    except Exception as exc:  # imageio raises many types for broken files
        raise RecordingError(path, f"unreadable PNG ({type(exc).__name__})") from None


class Recording:
    """A recording folder opened for reading; ``len(rec)``, ``rec[i]`` and iteration give frames."""

    def __init__(self, path: Path, meta: dict, camera: Camera, depth_files: list, color_files: list | None,
                 truth):
        self.path = path
        self.meta = meta
        self.camera = camera
        self.fps = float(meta["fps"])
        self.handedness = meta["handedness"]
        self._depth = depth_files
        self._color = color_files
        self.truth = truth

    @classmethod
    def open(cls, path) -> "Recording":
        path = Path(path)
        y = path / "recording.yaml"
        if not path.is_dir():
            raise RecordingError(path, "no such recording folder")
        if not y.is_file():
            raise RecordingError(y, "missing (not a recording folder)")
        meta = load_yaml(y, RecordingError)
        problem = schema_errors(meta if meta is not None else {}, "recording")
        if problem:
            raise RecordingError(y, problem)
        c = meta["camera"]
        cam = Camera(c["width"], c["height"], c["fx"], c["fy"], c["cx"], c["cy"], meta["depth"]["scale_m"],
                     meta["depth"]["encoding"], c.get("name", "custom"))
        n = meta["frames"]
        depth = [path / "depth" / f"{i:06d}.png" for i in range(n)]
        missing = [p.name for p in depth if not p.is_file()]
        if missing:
            raise RecordingError(path / "depth", f"missing frame file(s) {', '.join(missing[:5])}"
                                                 f"{' …' if len(missing) > 5 else ''} of {n}")
        color = None
        if meta.get("color"):
            color = [path / "color" / f"{i:06d}.png" for i in range(n)]
            miss = [p.name for p in color if not p.is_file()]
            if miss:
                raise RecordingError(path / "color", f"missing frame file(s) {', '.join(miss[:5])}")
        truth = None
        if meta.get("truth"):
            import pandas as pd

            tp = path / "truth.csv"
            if not tp.is_file():
                raise RecordingError(tp, "missing (recording.yaml says truth: true)")
            truth = pd.read_csv(tp, comment="#")
            need = ["frame", *_dof_names()]
            lack = [k for k in need if k not in truth.columns]
            if lack:
                raise RecordingError(tp, f"missing column(s) {', '.join(lack)}")
            if len(truth) != n:
                raise RecordingError(tp, f"{len(truth)} rows for {n} frames")
        return cls(path, meta, cam, depth, color, truth)

    def __len__(self) -> int:
        return len(self._depth)

    def __getitem__(self, i) -> Frame:
        if not -len(self) <= i < len(self):
            raise IndexError(i)
        i %= len(self)
        depth = decode_depth(_read_png(self._depth[i]), self.camera, self._depth[i])
        color = None
        if self._color is not None:
            color = np.asarray(_read_png(self._color[i]))[..., :3]
            if color.shape[:2] != depth.shape:
                raise RecordingError(self._color[i], "colour frame size differs from the depth frame")
        truth = None if self.truth is None else self.truth.iloc[i][_dof_names()].to_numpy(float)
        return Frame(i, i / self.fps, depth, color, truth)

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    def truth_array(self):
        return None if self.truth is None else self.truth[_dof_names()].to_numpy(float)


class RecordingWriter:
    """Write a recording folder frame by frame (each PNG atomically); metadata at :meth:`close`.

    Refuses a folder that exists and is not empty unless ``overwrite=True``."""

    def __init__(self, path, camera: Camera, fps: float = 30.0, handedness: str = "left", *, overwrite=False,
                 source: str = ""):
        self.path = Path(path)
        if self.path.exists() and any(self.path.iterdir()) and not overwrite:
            raise RecordingError(self.path, "exists and is not empty (never overwritten; use another folder)")
        if handedness not in ("left", "right"):
            raise RecordingError(self.path, f"handedness must be left or right, got {handedness!r}")
        if not fps > 0:
            raise RecordingError(self.path, f"fps must be positive, got {fps}")
        self.camera = camera
        self.fps = float(fps)
        self.handedness = handedness
        self.source = source
        self.n = 0
        self.truth = []
        self.color = None

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()

    def write(self, depth_m, color=None, truth=None) -> int:
        atomic_write_bytes(self.path / "depth" / f"{self.n:06d}.png", _png_bytes(encode_depth(depth_m, self.camera)))
        if self.color is None:
            self.color = color is not None
        if (color is not None) != self.color:
            raise RecordingError(self.path, "colour frames must be given for all frames or none")
        if color is not None:
            c = np.asarray(color)
            if c.shape != (self.camera.height, self.camera.width, 3) or c.dtype != np.uint8:
                raise RecordingError(self.path, f"colour frame must be {self.camera.height}×{self.camera.width}×3 uint8")
            atomic_write_bytes(self.path / "color" / f"{self.n:06d}.png", _png_bytes(c))
        if truth is not None:
            t = np.asarray(truth, float)
            if t.shape != (len(_dof_names()),):
                raise RecordingError(self.path, f"truth must have {len(_dof_names())} entries")
            self.truth.append(t)
        elif self.truth:
            raise RecordingError(self.path, "truth must be given for all frames or none")
        self.n += 1
        return self.n - 1

    def close(self):
        import yaml

        if self.truth and len(self.truth) != self.n:
            raise RecordingError(self.path, "truth must be given for all frames or none")
        if self.truth:
            import pandas as pd

            df = pd.DataFrame(np.array(self.truth), columns=_dof_names())
            df.insert(0, "time_s", np.arange(self.n) / self.fps)
            df.insert(0, "frame", np.arange(self.n))
            atomic_write_text(self.path / "truth.csv", df.to_csv(index=False, float_format="%.10g"), overwrite=True)
        cam = self.camera
        meta = {
            "schema_version": 1,
            "camera": {"name": cam.name, "width": cam.width, "height": cam.height, "fx": float(cam.fx),
                       "fy": float(cam.fy), "cx": float(cam.cx), "cy": float(cam.cy)},
            "depth": {"encoding": cam.depth_encoding, "scale_m": float(cam.depth_scale)},
            "fps": self.fps, "handedness": self.handedness, "frames": self.n,
            "color": bool(self.color), "truth": bool(self.truth),
            "created": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "generator": "synergistic-hand-tracking", "source": self.source,
        }
        self.path.mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.path / "recording.yaml", yaml.safe_dump(meta, sort_keys=False), overwrite=True)


def import_pngs(src, dst, camera: Camera, fps: float = 30.0, handedness: str = "left", progress=None) -> Recording:
    """Turn a plain folder of depth PNGs (natural sort order) into a recording (re-encoded losslessly
    in the camera's depth encoding)."""
    src = Path(src)
    files = sorted((p for p in src.glob("*.png") if p.is_file()), key=_natural_key) if src.is_dir() else []
    if not files:
        raise RecordingError(src, "no PNG files to import")
    with RecordingWriter(dst, camera, fps, handedness, source=str(src)) as w:
        for k, f in enumerate(files):
            d = decode_depth(_read_png(f), camera, f)
            w.write(d)
            if progress:
                progress(k + 1, len(files))
    return Recording.open(dst)
