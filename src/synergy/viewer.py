"""Synergies in the 3-D viewer: a Rerun ``.rrd`` of the hand swept along each principal component
(``synergy plot BUNDLE --rerun out.rrd``).

On the ``sweep`` timeline (``steps`` steps) every PC ``k`` sweeps its coefficient from −2σ to +2σ
(σ its standard deviation) at once, each hand beside the others:

==========================  ==========================================================================
entity                      what
==========================  ==========================================================================
``hands``                   static: the hand model's frame, y up (fingers along +y)
``hands/mean``              static: the mean posture's mesh, on the left
``hands/pc<k>``             static: where the hand of PC k stands (a translation along x)
``hands/pc<k>/mesh``        per step: the skinned mesh at μ + s·σ_k·c_k
``hands/pc<k>/skeleton``    per step: its bones
``sigma/pc<k>``             per step: s, the coefficient in units of σ_k
==========================  ==========================================================================

Needs the optional extra ``viz`` (rerun-sdk); without it, writing or reading a file is a
:class:`synergy.errors.SynergyError` naming the ``pip install``.
"""
from __future__ import annotations

import errno
from pathlib import Path

import numpy as np

from handmodel.fileio import atomic_path
from handmodel.model import HandModel
from handmodel.plots import FINGER_COLOURS

from .errors import SynergyError

try:  # an optional extra: the functions below name what to install when it is missing
    import rerun as rr
    from rerun.chunk import RrdReader
except ImportError:
    rr = RrdReader = None


def _require():
    if rr is None:
        raise SynergyError("--rerun", "the 3-D viewer needs rerun-sdk (pip install 'synergistic-hand-tracking[viz]')")

SKIN = (237, 194, 163)


def sweep(n_steps: int = 21, extent: float = 2.0) -> np.ndarray:
    """The coefficients of the sweep in units of σ: −extent … +extent in ``n_steps`` steps.

    >>> sweep(5).tolist()
    [-2.0, -1.0, 0.0, 1.0, 2.0]
    """
    if n_steps < 2:
        raise SynergyError("--steps", f"a sweep needs at least 2 steps, got {n_steps}")
    return np.linspace(-extent, extent, int(n_steps))


def _bones(hand, theta):
    kp = hand.keypoints(theta)
    par = np.asarray(hand.parents)
    child = np.flatnonzero(par >= 0)
    colours = [next((tuple(int(c[i:i + 2], 16) for i in (1, 3, 5)) for f, c in FINGER_COLOURS.items()
                     if hand.node_names[j].startswith(f)), (90, 90, 90)) for j in child]
    return np.stack([kp[par[child]], kp[child]], 1), np.array(colours, np.uint8)


def log_synergies(rec, bundle, *, n_pcs: int = 3, steps: int = 21, extent: float = 2.0, hand_model="default",
                  spacing: float = 0.16) -> list[int]:
    """Log the sweep of the first ``n_pcs`` PCs of ``bundle`` to the Rerun stream ``rec``; returns the PCs
    logged (1-based)."""
    _require()
    hand = HandModel.load(hand_model)
    model = bundle.model
    k = min(int(n_pcs), model.all_components_.shape[0])
    if k < 1:
        raise SynergyError("--pcs", f"needs at least 1 PC, got {n_pcs}")
    mesh = hand.mesh()
    post = ~hand.pose_mask

    def theta(coef_sd):
        th = np.zeros(hand.n_dofs)
        th[post] = model.posture(coef_sd)
        return th

    rec.log("hands", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
    mean = theta(np.zeros(k))
    rec.log("hands/mean", rr.Transform3D(translation=[-spacing, 0.0, 0.0]), static=True)
    rec.log("hands/mean/mesh", rr.Mesh3D(vertex_positions=mesh.pose(mean).astype(np.float32),
                                         triangle_indices=mesh.faces, albedo_factor=(200, 200, 200)), static=True)
    for r in range(k):
        ratio = 100 * model.all_explained_variance_ratio_[r]
        rec.log(f"hands/pc{r + 1}", rr.Transform3D(translation=[r * spacing, 0.0, 0.0]), static=True)
        rec.log(f"hands/pc{r + 1}/label", rr.TextDocument(f"PC{r + 1}: {ratio:.1f} % of the variance"), static=True)
    for i, s in enumerate(sweep(steps, extent)):
        rec.set_time("sweep", sequence=i)
        for r in range(k):
            th = theta(np.eye(r + 1)[r] * s)
            rec.log(f"hands/pc{r + 1}/mesh", rr.Mesh3D(vertex_positions=mesh.pose(th).astype(np.float32),
                                                       triangle_indices=mesh.faces, albedo_factor=SKIN))
            segs, colours = _bones(hand, th)
            rec.log(f"hands/pc{r + 1}/skeleton", rr.LineStrips3D(segs, colors=colours, radii=0.0015))
            rec.log(f"sigma/pc{r + 1}", rr.Scalars(float(s)))
    return list(range(1, k + 1))


def read_sweep(path) -> dict:
    """Entity → sorted ``sweep`` steps it holds, of a ``.rrd`` file (static entities left out)."""
    _require()
    out = {}
    for ch in RrdReader(Path(path)).stream():
        if ch.is_static or "sweep" not in ch.timeline_names:
            continue
        out.setdefault(ch.entity_path.lstrip("/"), set()).update(ch.to_record_batch().column("sweep").to_pylist())
    return {k: sorted(v) for k, v in out.items()}


def write_synergy_rrd(bundle, path, *, n_pcs: int = 3, steps: int = 21, extent: float = 2.0, hand_model="default",
                      overwrite: bool = False, spawn: bool = False) -> Path:
    """Write the sweep of :func:`log_synergies` to ``path`` (``.rrd``): to a temporary name, read
    back and checked to hold every step of every PC, then renamed into place. ``spawn`` also streams
    it to a Rerun viewer started now."""
    _require()
    path = Path(path)
    if path.suffix.lower() != ".rrd":
        raise SynergyError(path, "a Rerun recording must end in .rrd")
    rec = rr.RecordingStream("synergy")
    want = {}

    def check(tmp):
        try:
            got = read_sweep(tmp)
        except Exception as exc:  # rerun's reader raises its own types on a damaged file
            raise OSError(errno.EIO, f"the written Rerun file is unreadable ({exc})", str(path)) from None
        for ent, steps_ in want.items():
            if got.get(ent) != steps_:
                raise OSError(errno.EIO, f"the written Rerun file lacks steps of {ent}", str(path))

    with atomic_path(path, overwrite=overwrite, verify=check) as tmp:
        sinks = [rr.FileSink(str(tmp))]
        if spawn:
            rec.spawn(connect=False)
            sinks.append(rr.GrpcSink())
        rec.set_sinks(*sinks)
        rec.send_recording_name(f"{bundle.name}@{bundle.version}")
        pcs = log_synergies(rec, bundle, n_pcs=n_pcs, steps=steps, extent=extent, hand_model=hand_model)
        rec.flush()
        rec.disconnect()
        every = list(range(int(steps)))
        want = {f"hands/pc{k}/{part}": every for k in pcs for part in ("mesh", "skeleton")}
    return path
