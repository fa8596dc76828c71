"""The 3-D viewer: tracking logged to Rerun (``tracker track … --rerun out.rrd`` / ``--rerun-spawn``).

Per frame, on the ``frame`` (sequence) and ``time`` (seconds) timelines:

=========================  ==========================================================================
entity                     what
=========================  ==========================================================================
``world``                  static: the camera frame is the world (x right, y down, z forward)
``world/camera``           static: the pinhole camera (intrinsics, image size)
``world/camera/depth``     the depth image (millimetres, 0 = no data)
``world/camera/mask``      the segmentation (1 = the hand's pixels)
``world/points``           the segmented point cloud the fit used (metres)
``world/hand/mesh``        the fitted hand's skinned mesh (coloured by status)
``world/hand/skeleton``    its bones, one line per bone, coloured by finger
``world/hand/keypoints``   its 21 keypoints
``tracking/fit_mm``        fit error (mm)
``tracking/fps``           frames per second of the tracking step (1000 / ms)
``tracking/status``        tracked / lost / reinit, as a text log
=========================  ==========================================================================

A frame without a fit (nothing tracked yet) clears ``world/hand``. The ``.rrd`` file is written to a
temporary name, read back and checked to hold every logged frame, then renamed into place
(:class:`RerunLog`); :func:`read_frames` and :func:`read_frame` read a file back (the tests, and
:func:`snapshot_png`, a matplotlib picture of one logged frame for places without a viewer).

Needs the optional extra ``viz`` (rerun-sdk); without it, writing or reading a file is a
:class:`tracker.errors.TrackerError` naming the ``pip install``.
"""
from __future__ import annotations

import errno
import os
import shutil
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from handmodel.fileio import atomic_path
from handmodel.plots import FINGER_COLOURS

from .errors import TrackerError
from .plots import OVERLAY_COLOURS, depth_greys

try:  # an optional extra: the functions below name what to install when it is missing
    import rerun as rr
    from rerun.chunk import RrdReader
except ImportError:
    rr = RrdReader = None


def _require():
    if rr is None:
        raise TrackerError("--rerun", "the 3-D viewer needs rerun-sdk (pip install 'synergistic-hand-tracking[viz]')")

#: Entities logged on every frame (the hand's only where a fit exists).
FRAME_ENTITIES = ("world/camera/depth", "world/camera/mask", "world/points", "tracking/fit_mm",
                  "tracking/fps", "tracking/status")
HAND_ENTITIES = ("world/hand/mesh", "world/hand/skeleton", "world/hand/keypoints")
#: Mesh colour per status: skin when tracked, blue on a re-initialisation, red when lost.
STATUS_RGB = {"tracked": (237, 194, 163), "reinit": (120, 160, 230), "lost": (230, 90, 80)}


def _hex_rgb(h: str):
    return tuple(int(h[i:i + 2], 16) for i in (1, 3, 5))


def bone_colours(hand) -> np.ndarray:
    """``(n_bones, 3)`` uint8 colour of each bone (parent → node), by finger; the palm grey."""
    out = []
    for i, p in enumerate(hand.parents):
        if p >= 0:
            name = hand.node_names[i]
            out.append(next((_hex_rgb(c) for f, c in FINGER_COLOURS.items() if name.startswith(f)), (90, 90, 90)))
    return np.array(out, np.uint8).reshape(-1, 3)


def bones(hand, keypoints) -> np.ndarray:
    """``(n_bones, 2, 3)`` segments parent → node of the keypoints ``(n_nodes, 3)``."""
    kp = np.asarray(keypoints, float)
    child = np.flatnonzero(np.asarray(hand.parents) >= 0)
    return np.stack([kp[np.asarray(hand.parents)[child]], kp[child]], 1)


def _viewer_on_path() -> None:
    """Let Rerun find the viewer installed beside this Python (a virtualenv used without activating
    it has its ``rerun`` executable off ``PATH``)."""
    here = Path(sys.executable).parent
    if shutil.which("rerun") is None and (here / "rerun").exists():
        os.environ["PATH"] = str(here) + os.pathsep + os.environ.get("PATH", "")


def log_camera(rec, camera) -> None:
    """The static part: the world's axes and the pinhole camera."""
    rec.log("world", rr.ViewCoordinates.RDF, static=True)
    # Rerun puts pixel (0, 0)'s centre at (0.5, 0.5); ours is at (0, 0) (OpenCV)
    rec.log("world/camera", rr.Pinhole(focal_length=[camera.fx, camera.fy],
                                       principal_point=[camera.cx + 0.5, camera.cy + 0.5],
                                       resolution=[camera.width, camera.height],
                                       camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.3), static=True)
    rec.log("world/camera/mask", rr.AnnotationContext([(0, "background", (0, 0, 0, 0)),
                                                       (1, "hand", (255, 255, 255, 160))]), static=True)


def log_hand(rec, hand, theta, status, mesh=None) -> None:
    """The fitted hand at ``theta``: mesh (coloured by ``status``), skeleton and keypoints; a θ that is
    not finite clears ``world/hand``."""
    theta = np.asarray(theta, float)
    if not np.isfinite(theta).all():
        rec.log("world/hand", rr.Clear(recursive=True))
        return
    mesh = mesh if mesh is not None else hand.mesh()
    V = mesh.pose(theta)
    rec.log("world/hand/mesh", rr.Mesh3D(vertex_positions=V.astype(np.float32), triangle_indices=mesh.faces,
                                         albedo_factor=STATUS_RGB.get(status, (200, 200, 200))))
    kp = hand.keypoints(theta)
    rec.log("world/hand/skeleton", rr.LineStrips3D(bones(hand, kp), colors=bone_colours(hand), radii=0.0015))
    rec.log("world/hand/keypoints", rr.Points3D(kp, radii=0.003, colors=(20, 20, 20)))


class RerunLog:
    """Tracking logged frame by frame to a Rerun ``.rrd`` file and/or a spawned viewer.

    Parameters
    ----------
    camera : tracker.io.cameras.Camera
    path : the ``.rrd`` to write (None: only a spawned viewer); written to a temporary name and
        renamed into place by :meth:`close` after reading it back
    spawn : also start a Rerun viewer and stream to it (needs a screen)
    overwrite : replace an existing ``path``
    name : the recording's name shown in the viewer

    Attributes
    ----------
    frames_ : the frame indices logged
    warning_ : why a spawned viewer did not get everything (None: it did, or none was spawned)

    Use as a context manager, or call :meth:`close` (publishes the file) or :meth:`abort`.
    """

    def __init__(self, camera, path=None, *, spawn=False, overwrite=False, name="tracker"):
        _require()
        self.camera = camera
        self.path = None if path is None else Path(path)
        self.overwrite = overwrite
        self.frames_ = []
        self.warning_ = None
        self._meshes = {}
        self._last = None
        self._tmp = self._ctx = None
        self.rec = rr.RecordingStream("tracker")
        sinks = []
        if spawn:
            _viewer_on_path()
            try:
                self.rec.spawn(connect=False)
            except Exception as exc:  # the viewer binary or its port: rerun raises several types
                raise TrackerError("--rerun-spawn", f"cannot start the Rerun viewer ({exc})") from None
            sinks.append(rr.GrpcSink())
        if self.path is not None:
            if self.path.suffix.lower() != ".rrd":
                raise TrackerError(self.path, "a Rerun recording must end in .rrd")
            self._ctx = atomic_path(self.path, overwrite=overwrite, verify=self._verify)
            self._tmp = self._ctx.__enter__()
            sinks.append(rr.FileSink(str(self._tmp)))
        if sinks:
            self.rec.set_sinks(*sinks)
        self.rec.send_recording_name(str(name))
        log_camera(self.rec, camera)

    def log_frame(self, frame, result, observation, hand) -> None:
        """One tracked frame: ``frame`` (``index``, ``time_s``, ``depth`` metres), the tracker's
        ``result`` (:class:`tracker.track.FrameResult`), its ``observation`` (None for an unusable
        frame) and the ``hand`` model it was fitted with (it changes while a hand size is learnt)."""
        rec = self.rec
        rec.set_time("frame", sequence=int(frame.index))
        rec.set_time("time", duration=float(frame.time_s))
        H, W = self.camera.height, self.camera.width
        d = np.asarray(frame.depth if frame.depth is not None else np.full((H, W), np.nan), float)
        if d.shape != (H, W):
            d = np.full((H, W), np.nan)
        mm = np.where(np.isfinite(d), np.clip(np.round(d * 1000.0), 0, 65535), 0).astype(np.uint16)
        rec.log("world/camera/depth", rr.DepthImage(mm, meter=1000.0, colormap="turbo"))
        mask = np.zeros((H, W), np.uint8) if observation is None else np.asarray(observation.mask, np.uint8)
        rec.log("world/camera/mask", rr.SegmentationImage(mask))
        pts = np.zeros((0, 3)) if observation is None else np.asarray(observation.points, float)
        rec.log("world/points", rr.Points3D(pts, radii=0.001, colors=(40, 140, 255)))
        key = id(hand)
        if key not in self._meshes:
            self._meshes = {key: (hand, hand.mesh())}  # one size at a time: older ones are not needed again
        log_hand(rec, hand, result.theta, result.status, self._meshes[key][1])
        rec.log("tracking/fit_mm", rr.Scalars(float(result.fit_mm) if np.isfinite(result.fit_mm) else np.nan))
        rec.log("tracking/fps", rr.Scalars(1000.0 / result.ms if result.ms > 0 else np.nan))
        now = time.perf_counter()
        if self._last is not None and now > self._last:
            rec.log("tracking/fps_wall", rr.Scalars(1.0 / (now - self._last)))
        self._last = now
        rec.log("tracking/status", rr.TextLog(result.status, level="WARN" if result.status == "lost" else "INFO"))
        self.frames_.append(int(frame.index))

    def _verify(self, tmp: Path) -> None:
        """The written file holds every logged frame's entities (read back with Rerun's reader)."""
        try:
            got = read_frames(tmp)
        except Exception as exc:  # rerun's reader raises its own types on a damaged file
            raise OSError(errno.EIO, f"the written Rerun file is unreadable ({exc})", str(self.path)) from None
        want = set(self.frames_)
        for ent in FRAME_ENTITIES:
            if set(got.get(ent, ())) != want:
                raise OSError(errno.EIO, f"the written Rerun file lacks frames of {ent}", str(self.path))

    def close(self) -> Path | None:
        """Flush, then (with a file) read it back, check it and rename it into place; returns its path.

        A spawned viewer that went away (closed, or no screen to open on) does not cost the file:
        its reason is kept in ``warning_``."""
        try:
            self.rec.flush(timeout_sec=30.0)
        except RuntimeError as exc:  # the gRPC sink of a viewer that is gone; the file sink is checked below
            self.warning_ = f"the Rerun viewer was not reachable ({' '.join(str(exc).split())})"
        self.rec.disconnect()
        if self._ctx is None:
            return None
        ctx, self._ctx = self._ctx, None
        ctx.__exit__(None, None, None)
        return self.path

    def abort(self) -> None:
        """Stop logging and remove the unfinished file."""
        try:
            self.rec.disconnect()
        finally:
            if self._ctx is not None:
                ctx, self._ctx = self._ctx, None
                ctx.__exit__(RuntimeError, RuntimeError("aborted"), None)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self.abort()


# ----------------------------------------------------------------------------- reading back
def _chunks(path):
    _require()
    path = Path(path)
    if not path.is_file():
        raise TrackerError(path, "no such Rerun file")
    try:
        with warnings.catch_warnings():
            # a cut file also draws rerun's "no footer" warning: the error below is the one line to show
            warnings.simplefilter("ignore")
            return list(RrdReader(path).stream())
    except Exception as exc:  # rerun's reader raises its own types on a damaged file
        raise TrackerError(path, f"not a readable Rerun recording ({exc})") from None


def read_frames(path) -> dict:
    """Entity path → sorted list of the ``frame`` values it was logged at, of a ``.rrd`` file
    (static entities are left out)."""
    out = {}
    for ch in _chunks(path):
        if ch.is_static or "frame" not in ch.timeline_names:
            continue
        frames = ch.to_record_batch().column("frame").to_pylist()
        out.setdefault(ch.entity_path.lstrip("/"), set()).update(int(f) for f in frames)
    return {k: sorted(v) for k, v in out.items()}


def read_frame(path, frame: int) -> dict:
    """The components logged at ``frame`` of a ``.rrd`` file, per entity: ``{entity: {component:
    value}}`` with values as Python lists (e.g. ``"Points3D:positions"``), and the static ones."""
    out = {}
    for ch in _chunks(path):
        rb = ch.to_record_batch()
        ent = ch.entity_path.lstrip("/")
        if ch.is_static:
            rows = range(rb.num_rows)
        elif "frame" in ch.timeline_names:
            rows = [i for i, f in enumerate(rb.column("frame").to_pylist()) if f == frame]
        else:
            continue
        for i in rows:
            for name in rb.schema.names:
                if ":" in name:
                    out.setdefault(ent, {})[name] = rb.column(name)[i].as_py()
    return out


def snapshot_png(path, png, frame: int | None = None, *, overwrite=False) -> Path:
    """A picture of one frame of a ``.rrd`` file as logged (for places without a Rerun viewer): the
    depth image with the segmentation, and a 3-D view of the point cloud, the hand mesh and the
    skeleton. ``frame`` defaults to the last frame with a hand."""
    import io

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from handmodel.fileio import atomic_write_bytes

    frames = read_frames(path)
    if not frames.get("world/camera/depth"):
        raise TrackerError(path, "holds no tracked frames")
    logged = frames["world/camera/depth"]
    if frame is None:
        frame = (frames.get("world/hand/mesh") or logged)[-1]
    elif frame not in logged:
        raise TrackerError(path, f"holds no frame {frame} (frames {logged[0]}–{logged[-1]})")
    data = read_frame(path, frame)

    def comp(ent, name):
        return data.get(ent, {}).get(name)

    fig = Figure(figsize=(11, 5), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2, 1)
    img = comp("world/camera/depth", "DepthImage:buffer")
    fmt = comp("world/camera/depth", "DepthImage:format")
    col = OVERLAY_COLOURS
    if img is not None and fmt is not None:
        shape = (fmt[0]["height"], fmt[0]["width"])
        d = np.frombuffer(np.asarray(img[0], np.uint8).tobytes(), np.uint16).reshape(shape).astype(float)
        d = np.where(d > 0, d, np.nan)
        lo, hi = np.nanpercentile(d, [1, 99]) if np.isfinite(d).any() else (0.0, 1.0)
        im = ax.imshow(d, cmap=depth_greys(), vmin=lo, vmax=max(hi, lo + 1), interpolation="nearest")
        fig.colorbar(im, ax=ax, shrink=0.7, label="depth (mm)")
        m = comp("world/camera/mask", "SegmentationImage:buffer")
        if m is not None and np.any(m[0]):
            ax.contour(np.asarray(m[0], np.uint8).reshape(shape), [0.5], colors=[col["mask"]], linewidths=1.2)
        K = comp("world/camera", "Pinhole:image_from_camera")
        kp = comp("world/hand/keypoints", "Points3D:positions")
        strips = comp("world/hand/skeleton", "LineStrips3D:strips")
        if K is not None and kp is not None:
            # the fitted skeleton seen by the camera: Rerun keeps K column-major, pixel centres at +0.5
            K = np.asarray(K[0], float).reshape(3, 3).T
            to_px = lambda p: (K[0, 0] * p[..., 0] / p[..., 2] + K[0, 2] - 0.5,  # noqa: E731
                               K[1, 1] * p[..., 1] / p[..., 2] + K[1, 2] - 0.5)
            for s in strips or ():
                u, v = to_px(np.asarray(s, float))
                ax.plot(u, v, "-", color=col["bone"], lw=1.5)
            u, v = to_px(np.asarray(kp, float).reshape(-1, 3))
            ax.plot(u[0], v[0], "s", color=col["wrist"], mec="w", ms=8, mew=1)  # the first keypoint is the wrist
        ax.set_xlim(-0.5, shape[1] - 0.5)
        ax.set_ylim(shape[0] - 0.5, -0.5)
    ax.set_title(f"frame {frame}: depth, mask (green), fitted skeleton, wrist (blue)", fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    ax3 = fig.add_subplot(1, 2, 2, projection="3d", proj_type="persp")
    pts = np.asarray(comp("world/points", "Points3D:positions") or np.zeros((0, 3)), float).reshape(-1, 3) * 1000
    V = comp("world/hand/mesh", "Mesh3D:vertex_positions")
    F = comp("world/hand/mesh", "Mesh3D:triangle_indices")
    every = []
    if V is not None and F is not None:
        V = np.asarray(V, float).reshape(-1, 3) * 1000
        F = np.asarray(F, int).reshape(-1, 3)
        ax3.add_collection3d(Poly3DCollection(V[F], facecolors=(0.93, 0.76, 0.64, 0.35), edgecolors="none"))
        every.append(V)
    strips = comp("world/hand/skeleton", "LineStrips3D:strips")
    if strips is not None:
        rgba = comp("world/hand/skeleton", "LineStrips3D:colors") or [0x000000FF] * len(strips)
        for s, c in zip(strips, rgba):
            s = np.asarray(s, float) * 1000
            colour = [(int(c) >> k & 255) / 255 for k in (24, 16, 8)]  # Rerun packs colours as RGBA u32
            ax3.plot(s[:, 0], s[:, 1], s[:, 2], "-", color=colour, lw=2)
    kp3 = comp("world/hand/keypoints", "Points3D:positions")
    if kp3 is not None:
        w = np.asarray(kp3, float).reshape(-1, 3)[0] * 1000
        ax3.plot([w[0]], [w[1]], [w[2]], "s", color=col["wrist"], mec="w", ms=8)
    if len(pts):
        ax3.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=1, c="tab:blue", depthshade=False)
        every.append(pts)
    if every:
        allp = np.vstack(every)
        c, r = (allp.min(0) + allp.max(0)) / 2, (allp.max(0) - allp.min(0)).max() / 2 + 5
        ax3.set(xlim=(c[0] - r, c[0] + r), ylim=(c[1] - r, c[1] + r), zlim=(c[2] - r, c[2] + r))
    ax3.set_box_aspect((1, 1, 1))
    ax3.view_init(elev=-70, azim=-90)  # looking along the camera's z, y down: as the camera sees it
    ax3.set(xlabel="x mm", ylabel="y mm", zlabel="z mm")
    fit = comp("tracking/fit_mm", "Scalars:scalars")
    status = comp("tracking/status", "TextLog:text")
    ax3.set_title(f"points used, fitted hand ({status[0] if status else '-'}, fit "
                  f"{np.ravel(fit)[0]:.1f} mm)" if fit is not None else "points used, fitted hand", fontsize=9)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return atomic_write_bytes(png, buf.getvalue(), overwrite=overwrite)
