"""Making a recording folder from what a user has: a recording file (:func:`import_recording_file`),
a folder of depth PNGs (:func:`import_pngs`) or stills (:func:`import_stills`)."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from ..errors import RecordingError
from .base import list_pngs, natural_sorted
from .cameras import Camera, as_camera
from .files import open_recording_file
from .folder import Recording
from .images import read_bytes, read_color, read_depth_units
from .writer import RecordingWriter


def import_recording_file(src, dst, *, topic=None, color_topic=None, start_s=None, end_s=None, every: int = 1,
                          handedness: str = "left", overwrite: bool = False, progress=None) -> Recording:
    """Convert a recording file (see :func:`open_recording_file`) into a recording folder.

    Integer depth is copied unit for unit; float depth (ROS ``32FC1``, metres) is rounded to the
    camera's unit (1 mm). The folder's fps is the file's divided by ``every``; its frame times are
    ``i / fps`` (a folder stores no per-frame times), the file's own times stay in the file.

    Parameters
    ----------
    src : recording file
    dst : recording folder to create
    topic, color_topic : ROS depth and colour topics (default: found in the file)
    start_s, end_s : time span to keep (seconds from the file's first depth frame, both included)
    every : keep every N-th frame of the span
    handedness, overwrite : as for :class:`RecordingWriter`
    progress : callable ``progress(done, total)``, called after each frame

    Returns
    -------
    Recording
        The new recording folder, opened.
    """
    src = Path(src)
    rec = open_recording_file(src, topic=topic, color_topic=color_topic, handedness=handedness)
    rec = rec.select(start_s, end_s, every)
    if not len(rec):
        raise RecordingError(src, "holds no depth frames to import")
    with RecordingWriter(dst, rec.camera, rec.fps / every, handedness, overwrite=overwrite,
                         source=f"import of {src} ({rec.source})") as w:
        for i in range(len(rec)):
            frame, units = rec.frame_with_units(i)
            w.write_units(units, frame.color)
            if progress is not None:
                progress(i + 1, len(rec))
    return Recording.open(dst)



COLOR_SUFFIXES = (".png", ".jpg", ".jpeg")


def import_color(path, camera: Camera) -> np.ndarray:
    """One colour frame to import: 8-bit RGB(A) PNG or JPEG of the camera's size, registered to the
    depth image (the same pixel grid), as ``(H, W, 3)`` uint8."""
    path = Path(path)
    if path.suffix.lower() == ".png":
        return read_color(path, camera)
    import imageio.v3 as iio

    data = read_bytes(path)
    try:
        a = np.asarray(iio.imread(data, extension=".jpg", plugin="pillow"))
    except Exception as exc:  # Pillow raises many types for damaged files
        raise RecordingError(path, f"unreadable JPEG ({type(exc).__name__}: {exc})") from None
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] < 3:
        raise RecordingError(path, f"colour frames need 8-bit RGB, got {a.dtype} {a.shape}")
    if a.shape[:2] != (camera.height, camera.width):
        raise RecordingError(path, f"image is {a.shape[1]}×{a.shape[0]}, the camera says {camera.width}×{camera.height}")
    return np.ascontiguousarray(a[..., :3])


def _png_sources(src: Path, dst, color):
    """The depth PNGs of ``src`` and their colour frames (or None), in natural name order."""
    files = list_pngs(src)
    if not files:
        raise RecordingError(src, "no PNG files to import")
    if Path(dst).resolve() == src.resolve():
        raise RecordingError(dst, "the recording folder must differ from the source folder")
    colors = None
    if color is not None:
        cdir = Path(color)
        if not cdir.is_dir():
            raise RecordingError(cdir, "no such folder")
        colors = natural_sorted(p for p in cdir.iterdir() if p.suffix.lower() in COLOR_SUFFIXES
                                and not p.name.startswith(".") and p.is_file())
        if len(colors) != len(files):
            raise RecordingError(cdir, f"{len(colors)} colour frames for {len(files)} depth frames in {src}")
    return files, colors


def import_stills(src, dst, camera, fps: float = 30.0, handedness: str = "left", *, overwrite: bool = False,
                  progress=None, color=None) -> list[Recording]:
    """Turn a folder of still depth PNGs — single frames, not a video — into one recording per PNG,
    ``dst/<file stem>/``, so that ``tracker track dst/*`` fits each from its own first frame
    (tracked as one recording, each frame would start from the fit of the one before).

    Parameters and checks as :func:`import_pngs`; ``dst`` must be empty or new, or with ``overwrite``
    hold only recordings (they are replaced). A failure removes every recording this call wrote.

    Returns
    -------
    list of Recording
        The new recordings, opened, in natural name order.
    """
    src, dst = Path(src), Path(dst)
    files, colors = _png_sources(src, dst, color)
    camera = as_camera(camera)
    stems = [f.stem for f in files]
    twins = sorted({s for s in stems if stems.count(s) > 1})
    if twins:
        raise RecordingError(src, f"two PNGs are named {twins[0]} (e.g. .png and .PNG): one recording each needs "
                                  "distinct names")
    if dst.exists() and not dst.is_dir():
        raise RecordingError(dst, "exists and is not a folder")
    old = sorted(dst.iterdir()) if dst.exists() else []
    if old and not overwrite:
        raise RecordingError(dst, "exists and is not empty (never overwritten; use another folder, or --overwrite)")
    alien = [e.name for e in old if not (e.is_dir() and (e / "recording.yaml").is_file())]
    if alien:
        raise RecordingError(dst, f"holds {', '.join(alien[:3])}, not recordings; refusing to overwrite")
    for e in old:
        RecordingWriter(e, camera, fps, handedness, overwrite=True).abort()  # clears a recording, nothing else
        shutil.rmtree(e, ignore_errors=True)
    created = not dst.exists()
    done = []
    try:
        for k, f in enumerate(files):
            with RecordingWriter(dst / f.stem, camera, fps, handedness, source=f"import of {f} (a still frame)") as w:
                w.write_units(read_depth_units(f, camera), None if colors is None else import_color(colors[k], camera))
            done.append(dst / f.stem)
            if progress is not None:
                progress(k + 1, len(files))
    except BaseException:
        for d in done:
            shutil.rmtree(d, ignore_errors=True)
        if created:
            shutil.rmtree(dst, ignore_errors=True)
        raise
    return [Recording.open(d) for d in done]


def import_pngs(src, dst, camera, fps: float = 30.0, handedness: str = "left", *, overwrite: bool = False,
                progress=None, color=None) -> Recording:
    """Turn a plain folder of depth PNGs (natural name order) into a recording.

    Every PNG must match the camera: its size and the depth encoding's PNG type (16-bit greyscale
    for ``uint16``, 8-bit RGB for ``nyu_rgb``). The stored units are copied exactly.

    Parameters
    ----------
    src : folder of PNGs
    dst : recording folder to create
    camera : Camera (e.g. ``preset("sr305")``)
    fps, handedness, overwrite : as for :class:`RecordingWriter`
    progress : callable ``progress(done, total)``, called after each frame
    color : optional folder of colour frames registered to the depth (PNG or JPEG, natural name
        order, one per depth frame), for skin segmentation

    Returns
    -------
    Recording
        The new recording, opened.
    """
    src = Path(src)
    files, colors = _png_sources(src, dst, color)
    camera = as_camera(camera)
    # the frames are renumbered: the source line keeps which files, in which order, they came from
    names = files[0].name if len(files) == 1 else f"{files[0].name} … {files[-1].name}"
    source = f"import of {src} ({len(files)} PNG{'s' if len(files) > 1 else ''}, {names}, in natural name order)"
    with RecordingWriter(dst, camera, fps, handedness, overwrite=overwrite, source=source) as w:
        for k, f in enumerate(files):
            w.write_units(read_depth_units(f, camera), None if colors is None else import_color(colors[k], camera))
            if progress is not None:
                progress(k + 1, len(files))
    return Recording.open(dst)
