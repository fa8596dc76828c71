"""Synthetic recordings: a motion rendered through a camera, with sensor noise, written as a
recording folder with the true θ of every frame (``truth.csv``).

Frame ``i`` is :class:`~tracker.sim.render.DepthRenderer` output at the motion's θ, degraded by a
:class:`~tracker.sim.noise.NoiseModel` with ``default_rng([seed, i])``, so a recording is
reproducible from its seed. The rendered hand may be resized (:class:`~tracker.sim.hands.HandShape`);
``truth_hand.yaml`` beside ``truth.csv`` records its shape (:func:`~tracker.sim.hands.truth_hand`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from handmodel import HandModel
from handmodel.rigid import euler_to_matrix

from ..errors import TrackerError
from ..io.recording import RecordingWriter
from .hands import HandShape, wrist_to_middle_tip_mm, write_hand_truth
from .motions import Motion, hand_centre, make_motion
from .noise import NoiseModel
from ..io.cameras import as_camera
from .clutter import Clutter
from .render import DepthRenderer


@dataclass(frozen=True)
class SynthesisReport:
    """What :func:`synthesize` wrote."""

    path: Path
    motion: str
    frames: int
    fps: float
    camera: str
    noise: str
    hand_pixels: float  # mean rendered hand pixels per frame
    valid_fraction: float  # of rendered hand pixels that keep depth after noise
    clutter_pixels: float  # mean pixels per frame showing clutter (rendered)
    depth_range_m: tuple  # min, max hand depth over all frames (rendered)
    render_ms: float  # mean per frame, LBS + raster (+ colour)
    noise_ms: float
    seconds: float
    hand_scale: float = 1.0
    hand_length_mm: float = float("nan")  # rendered hand, wrist to middle tip


def _resolve(motion, camera, noise, hand, frames, fps, seed):
    if not fps > 0:
        raise TrackerError("fps", f"must be positive, got {fps}")
    if isinstance(motion, Motion):
        m = motion.resample(fps).head(frames)
    else:
        m = make_motion(motion, hand=hand, frames=frames, fps=fps, seed=seed)
    cam = as_camera(camera)
    nm = NoiseModel.preset(noise) if isinstance(noise, str) else (noise or NoiseModel.preset("none"))
    if not isinstance(nm, NoiseModel):
        raise TrackerError("noise", "needs a NoiseModel or a preset name")
    return m, cam, nm


def synthesize(motion, camera, noise, out_dir, fps: float = 30, seed: int = 0,
               progress: Callable[[int, int], None] | None = None, *, hand=None, frames: int | None = None,
               clutter: Clutter | str | None = None, color: bool = False, shape: HandShape | None = None,
               **writer_options) -> SynthesisReport:
    """Render a motion, add sensor noise and write a recording folder with the true θ per frame.

    Parameters
    ----------
    motion : Motion, scenario name or motion file (see :func:`tracker.sim.motions.make_motion`)
        A :class:`Motion` at another frame rate is resampled to ``fps``.
    camera : camera object or preset name
    noise : NoiseModel or preset name (``none``, ``kinect1``)
    out_dir : folder to create (via :class:`tracker.io.recording.RecordingWriter`)
    fps, seed : frame rate; noise of frame ``i`` uses ``default_rng([seed, i])``
    progress : called as ``progress(done, total)`` after each frame
    hand : HandModel (default: the default left hand); the tracking model the truth θ refers to
    frames : at most this many frames
    clutter : Clutter or a :meth:`Clutter.parse` spec; torso, table and object stay where the
        motion's mean hand centre puts them
    color : also write colour frames
    shape : HandShape of the rendered hand relative to ``hand`` (default: the same size); recorded
        in ``truth_hand.yaml``
    writer_options : passed to ``RecordingWriter``
    """
    if hand is None:
        hand = HandModel.load()
    shape = shape or HandShape()
    shown = shape.apply(hand)
    m, cam, nm = _resolve(motion, camera, noise, shown, frames, fps, seed)
    if isinstance(clutter, str):
        clutter = Clutter.parse(clutter)
    renderer = DepthRenderer(shown, cam)
    if clutter is not None:
        R = euler_to_matrix(m.theta[:, 3:6])
        centres = m.theta[:, :3] + R @ hand_centre(shown)
        clutter = clutter.sized(shape.scale).fixed(centres.mean(axis=0))
    t_start = time.perf_counter()
    t_render = t_noise = 0.0
    n_hand = n_valid = n_clutter = 0
    zmin, zmax = np.inf, -np.inf
    cam_name = getattr(cam, "name", None) or (camera if isinstance(camera, str) else "custom")
    clutter_desc = "none" if clutter is None else clutter.describe()
    writer_options.setdefault("source", f"synthetic: motion {m.name}, noise {nm.name}, seed {seed}, "
                                        f"clutter {clutter_desc}, hand {hand.name} ({hand.handedness}) "
                                        f"scale {shape.scale:g}, finger scales "
                                        f"{','.join(f'{v:g}' for v in shape.finger_scales().values())}")
    with RecordingWriter(out_dir, cam, float(fps), hand.handedness, **writer_options) as writer:
        for i, th in enumerate(m.theta):
            t0 = time.perf_counter()
            r = renderer.render(th, labels=True, color=color, clutter=clutter, incidence=nm.needs_incidence,
                                reflectance=nm.needs_reflectance)
            t1 = time.perf_counter()
            depth = r.depth if nm.is_noise_free else nm.apply(r.depth, cam, np.random.default_rng([seed, i]),
                                                             r.cos_incidence, r.reflectance)
            t2 = time.perf_counter()
            t_render += t1 - t0
            t_noise += t2 - t1
            hm = r.labels >= 0
            n_hand += int(hm.sum())
            n_clutter += int((r.labels < -1).sum())
            n_valid += int(np.isfinite(depth[hm]).sum())
            if hm.any():
                zmin, zmax = min(zmin, float(r.depth[hm].min())), max(zmax, float(r.depth[hm].max()))
            writer.write(depth, color=r.color if color else None, truth=np.asarray(th))
            if progress is not None:
                progress(i + 1, m.frames)
        # inside the writer: recording.yaml, written last on closing, marks a finished recording
        write_hand_truth(out_dir, shape, hand)
    F = m.frames
    return SynthesisReport(
        path=Path(out_dir), motion=m.name, frames=F, fps=float(fps), camera=str(cam_name), noise=nm.name,
        hand_pixels=n_hand / F, valid_fraction=(n_valid / n_hand) if n_hand else 0.0, clutter_pixels=n_clutter / F,
        depth_range_m=(zmin, zmax) if n_hand else (float("nan"), float("nan")),
        render_ms=1000 * t_render / F, noise_ms=1000 * t_noise / F, seconds=time.perf_counter() - t_start,
        hand_scale=shape.scale, hand_length_mm=wrist_to_middle_tip_mm(shown),
    )
