"""Subject calibration: the subject's hand (bone lengths, finger bases) and where each marker sits on it.

Anchors: OpenSim's Scale tool (scale, then place markers) and the functional calibrations of finger
mocap (Cerveri et al. 2007, Gustus et al. 2012), which fit joint centres and segment lengths to the
markers' motion. Three routes, chosen by what the marker set makes observable:

1. **Joint-centre protocols** (a marker at the joint centre at both ends of every bone, e.g. ART's
   export): bone lengths are measured directly, finger bases placed and oriented where the data has them.
2. **Skin or glove markers**: first one hand scale (golden-section search on the marker-IK residual),
   then a joint estimate of every observable bone length (each phalanx, the thumb's bones), each finger
   base's place on the palm (the metacarpals) and each marker's place on its bone, together with the
   postures of the calibration frames (Gauss-Newton on all of it, the postures eliminated by a Schur
   complement). Each marker's nominal place and its uncertainty (``offset_sd`` in the marker set) and
   a prior on bone lengths (``bone_sd``) are part of the objective, so weakly observed quantities stay
   at their nominal values instead of absorbing noise.
3. **Held-out check**: the calibration frames are blocks of the trial; other blocks are held out. The
   median marker residual on them (the median over frames of a frame's RMS marker distance, as in the
   conversion's table), for the calibrated hand and for the scale-only hand, says whether the extra
   freedom generalises. A calibration whose held-out residual is above the scale-only hand's, or
   clearly above its own training residual without being clearly below the scale-only hand's, is
   flagged ``overfit`` (:func:`synergy.subject.overfits`; :func:`markers_to_angles` then falls back
   to the scale-only hand).

Examples
--------
>>> from synergy.simulate import motion, simulate_markers
>>> from handmodel import HandModel
>>> from synergy.markers import load_markerset
>>> th, _ = motion("open_close", duration_s=1.0, seed=1)
>>> tr = simulate_markers(th, "hand16", scale=1.1)
>>> cal = calibrate(tr, load_markerset("hand16"), HandModel.load(), subject=False)
>>> round(cal.scale, 2)
1.1
"""
from __future__ import annotations

import hashlib
from copy import deepcopy
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import yaml
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from handmodel.fileio import atomic_write_text, load_yaml, plain_values, schema_errors, sha256_file
from handmodel.solver import SolverSettings, fit_points

from .errors import MarkerSetError, SynergyError
from .smoothing import lowpass_markers
from .subject import refine_subject

#: Version of the subject-calibration file (``data_schema/subject-calibration.schema.json``).
CALIBRATION_VERSION = 1
#: Default prior SD of a bone's length relative to the hand-scaled model (fraction).
BONE_SD = 0.25
#: Default low-pass cut-off (Hz) of the calibration trials' markers. Each calibration frame's posture
#: is fitted together with the subject, so the part of a frame's noise its posture cannot absorb
#: pulls the subject's numbers off, by an amount more frames do not shrink (hand16, seed 4: the
#: index's middle phalanx 2.7 mm long from 150 frames and from 400, 0.3 mm from noise-free markers).
#: Hand motion lies well below 6 Hz (the usual cut-off for human movement), 0.5 mm of white noise
#: at 100 Hz drops to ~0.2 mm (simulated subjects, power-grasp angles: hand16 1.38–3.81° → see the
#: calibration table in docs/synergy.md).
SMOOTH_HZ = 6.0
#: Without a static trial, frames whose finger flexions (MCP, PIP, DIP; the scale-only hand's IK) all
#: stay below this (degrees) are taken as the flat hand (:func:`neutral_frames`) …
NEUTRAL_DEG = 30.0
#: … held to it with this SD (degrees; a static trial's is 3°): a relaxed open hand is not exactly flat.
NEUTRAL_SD_DEG = 8.0
#: … when at least this many such frames exist (of up to 30 taken, the most open ones).
NEUTRAL_MIN_FRAMES = 5


@dataclass
class Calibration:
    """The subject's hand and marker placement as estimated, with uncertainties and checks.

    ``scale`` resizes the whole hand; ``bone_scales`` (node → factor) resize single bones on top;
    ``joint_positions`` (finger base → metres in the palm frame) and ``joint_rotations`` place the
    finger bases; ``offsets`` (label → metres in its node's frame) place markers. ``uncertainty``
    holds one SD per estimated number (same keys; mm for positions); ``held_out`` the check on
    frames not used for fitting; ``warnings`` what a user should know.
    """

    scale: float = 1.0
    bone_scales: dict = field(default_factory=dict)
    joint_positions: dict = field(default_factory=dict)
    joint_rotations: dict = field(default_factory=dict)
    offsets: dict = field(default_factory=dict)
    frames_used: int = 0
    median_residual_mm: float = float("nan")
    method: str = "none"
    source: str = ""
    source_sha256: str = ""
    static_source: str = ""
    hand: str = ""
    markerset: str = ""
    hand_model: str = ""
    uncertainty: dict = field(default_factory=dict)
    marker_shift_mm: dict = field(default_factory=dict)
    held_out: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)

    def model(self, hand):
        """The calibrated hand model."""
        m = hand.scaled(self.scale, self.bone_scales)
        if self.joint_positions:
            m = m.with_joint_positions(self.joint_positions)
        if self.joint_rotations:
            m = m.with_rest_rotations(self.joint_rotations)
        return m

    @property
    def overfit(self) -> bool:
        return bool(self.held_out.get("overfit", False))

    def summary(self) -> str:
        """One line: what was estimated and how well it generalises."""
        parts = [self.method]
        if self.bone_scales:
            f = np.array(list(self.bone_scales.values()))
            parts.append(f"{len(f)} bones {f.min():.2f}–{f.max():.2f}×")
        if self.joint_positions:
            parts.append(f"{len(self.joint_positions)} finger bases")
        if self.marker_shift_mm:
            s = np.array(list(self.marker_shift_mm.values()))
            parts.append(f"markers moved median {np.median(s):.1f} mm (max {s.max():.1f})")
        if self.held_out.get("frames"):
            parts.append(held_out_line(self.held_out))
        return "; ".join(parts)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["offsets"] = {k: [float(x) for x in v] for k, v in self.offsets.items()}
        d["bone_scales"] = {k: float(v) for k, v in self.bone_scales.items()}
        d["joint_positions"] = {k: [float(x) for x in v] for k, v in self.joint_positions.items()}
        d["joint_rotations"] = {k: np.asarray(v, float).tolist() for k, v in self.joint_rotations.items()}
        d["marker_shift_mm"] = {k: float(v) for k, v in self.marker_shift_mm.items()}
        d["uncertainty"] = plain_values(self.uncertainty)
        d["held_out"] = plain_values(self.held_out)
        d["scale"] = float(self.scale)
        d["median_residual_mm"] = float(self.median_residual_mm)
        return d

    @classmethod
    def from_dict(cls, d) -> "Calibration":
        return cls(**{k: d[k] for k in cls.__dataclass_fields__ if k in d})


# ------------------------------------------------------------------------------------------ frames
def sample_frames(points, count):
    """Up to ``count`` frames spread over the trial, preferring frames with every marker present."""
    present = ~np.isnan(points[..., 0])
    full = np.flatnonzero(present.all(1))
    pool = full if len(full) >= min(count, 20) else np.flatnonzero(present.sum(1) >= 3)
    if len(pool) == 0:
        return pool
    take = np.linspace(0, len(pool) - 1, min(count, len(pool))).round().astype(int)
    return np.unique(pool[take])


def split_frames(points, count, held_out=0.25, blocks=8):
    """Training and held-out frame indices: the trial cut into ``blocks`` runs, every
    ``round(1 / held_out)``-th run held out, so held-out frames are not neighbours of training
    frames (neighbouring frames share the same posture and would hide overfitting).

    >>> tr, ho = split_frames(np.zeros((400, 5, 3)), 100)
    >>> len(tr) > 0 and len(ho) > 0 and not set(tr) & set(ho)
    True
    """
    present = ~np.isnan(points[..., 0])
    pool = np.flatnonzero(present.sum(1) >= 3)
    if len(pool) == 0 or held_out <= 0:
        return sample_frames(points, count), np.zeros(0, np.int64)
    every = max(int(round(1 / held_out)), 2)
    nb = max(blocks, every)
    block = np.minimum((np.arange(len(pool)) * nb) // len(pool), nb - 1)
    hold = (block % every) == every - 1
    tr_pool, ho_pool = pool[~hold], pool[hold]
    n_ho = max(int(round(count * held_out / (1 - held_out))), 1)
    sub = np.zeros_like(points[..., 0], bool)
    sub[tr_pool] = True
    pts_tr = np.where(sub[..., None], points, np.nan)
    train = sample_frames(pts_tr, count)
    take = np.linspace(0, len(ho_pool) - 1, min(n_ho, len(ho_pool))).round().astype(int)
    return train, np.unique(ho_pool[take]) if len(ho_pool) else np.zeros(0, np.int64)


# ------------------------------------------------------------------------------------ joint centres
def neutral_frames(model, nodes, local, targets, weights, *, frames=300, limit_deg=None, take=30):
    """The trial's most neutral frames (indices into ``targets``): solved on the (scale-only) hand,
    the frames whose largest finger flexion (MCP, PIP, DIP of the four fingers) stays below
    ``limit_deg`` (default :data:`NEUTRAL_DEG`), the ``take`` most open first; fewer than
    :data:`NEUTRAL_MIN_FRAMES` is none."""
    limit_deg = NEUTRAL_DEG if limit_deg is None else limit_deg
    sel = sample_frames(targets, frames)
    if not len(sel):
        return np.zeros(0, np.int64)
    th, rep = fit_points(model, nodes, local, targets[sel], weights=weights,
                         settings=SolverSettings(iterations=15, damping=0.1), restarts=1)
    names = list(model.dof_names)
    flex = [names.index(f"{f}{k}_flex") for f in ("index", "middle", "ring", "pinky") for k in (1, 2, 3)
            if f"{f}{k}_flex" in names]
    worst = np.degrees(np.abs(th[:, flex])).max(1)
    worst[rep.iterations < 0] = np.inf
    order = np.argsort(worst)
    keep = order[worst[order] < limit_deg][:take]
    return np.sort(sel[keep]) if len(keep) >= NEUTRAL_MIN_FRAMES else np.zeros(0, np.int64)


def _joint_centre_bones(hand, markerset, nodes, local, targets):
    """Bone factors from markers sitting at the joint centres at both ends of a bone."""
    at_centre = {int(n): i for i, (n, l) in enumerate(zip(nodes, local)) if not np.any(l)}
    out = {}
    for child, i in at_centre.items():
        par = int(hand.parents[child])
        if par < 0 or par not in at_centre:
            continue
        d = np.linalg.norm(targets[:, i] - targets[:, at_centre[par]], axis=1)
        d = d[np.isfinite(d)]
        model = np.linalg.norm(hand.rest[child, :3, 3])
        if len(d) and model > 0:
            out[hand.node_names[child]] = float(np.median(d) / model)
    return out


def _orient_finger_bases(hand, nodes, local, palm, residual, cal):
    """Rest rotation of each finger base that best explains its finger's joint centres (the plane
    the finger flexes in differs between people and tracking systems): a small rotation, 3 numbers
    per finger, fitted by Nelder–Mead on the finger's marker residual after IK."""

    rots = {}
    for i in palm:
        base = int(nodes[i])
        chain = [k for k, n in enumerate(nodes) if _descends(hand, int(n), base)]
        if len(chain) < 3:
            continue
        name = hand.node_names[base]
        R0 = hand.scaled(1.0, cal.bone_scales).rest[base, :3, :3]
        sel = slice(None, None, 3)

        def cost(r):
            R = Rotation.from_rotvec(r).as_matrix() @ R0
            return residual(1.0, cal.bone_scales, None, cal.joint_positions, {**rots, name: R}, sel, chain)[0]

        res = minimize(cost, np.zeros(3), method="Nelder-Mead",
                       options={"xatol": 1e-3, "fatol": 1e-3, "maxfev": 120, "initial_simplex": 0.15 * np.vstack([np.zeros(3), np.eye(3)])})
        # only a clear improvement re-orients the base: where the model already explains the finger,
        # a rotated base would fit as well and merely change what the angles mean
        if res.fun < 0.8 * cost(np.zeros(3)) - 0.1:
            rots[name] = Rotation.from_rotvec(res.x).as_matrix() @ R0
    return rots


def _descends(hand, node, base):
    while node >= 0:
        if node == base:
            return True
        node = int(hand.parents[node])
    return False


def calibrate(data, markerset, hand, *, right=False, frames=150, offset_iterations=3, scale_range=(0.6, 1.6),
              settings=None, orient_bases=True, subject=True, held_out=0.25, bone_sd=BONE_SD, offset_scale=1.0,
              data_sd_mm=1.0, iterations=25, static=None, static_posture=None, static_sd_deg=3.0,
              require_gain=None, smooth_hz=SMOOTH_HZ, posture_prior=None, prior_frames=None,
              neutral=False) -> Calibration:
    """Estimate the subject's hand from a trial (``data``: marker data with ``labels``/``points``).

    Parameters
    ----------
    data : marker data (a range-of-motion trial, a static trial or the trial itself)
    markerset : :class:`~synergy.markers.MarkerSet` for the chosen hand
    hand : the (mirrored, for right) hand model to calibrate
    frames : calibration frames (spread over the trial)
    subject : for skin/glove markers, also estimate bone lengths, finger bases and marker places
        (route 2); False stops after the hand scale (and the ``calibrate_offset`` markers)
    held_out : share of the sampled frames held out to check the calibration (0: no check)
    bone_sd, offset_scale : prior SD of bone lengths (fraction), multiplier on every marker's
        ``offset_sd`` (a large value gives the calibration too much freedom; the held-out check says so)
    data_sd_mm : assumed marker noise that weighs the data against the priors
    require_gain : keep the subject fit only if its held-out residual is below this share of the
        scale-only one (automatic calibration: extra freedom must pay for itself); None keeps it
    static : marker data of a static trial in a known posture (``static_posture``, 20 angles; default
        the flat hand) to fit together with ``data`` (a static + range-of-motion pair)
    smooth_hz : zero-phase low-pass cut-off (Hz) of the markers before calibrating (see
        :data:`SMOOTH_HZ`); None or 0 fits the raw markers
    neutral : without a static trial, use the trial's most neutral frames (:func:`neutral_frames`)
        as one, held to the flat hand with :data:`NEUTRAL_SD_DEG`
    posture_prior, prior_frames : without a static trial (or neutral frames), a
        :class:`~synergy.prior.PosturePrior` on the calibration frames' postures, weighed as
        ``prior_frames`` postures in all (None: as many as the frames)

    Returns a :class:`Calibration`; ``Calibration.model(hand)`` is the calibrated model and its
    ``scale`` and ``offsets`` go to :meth:`MarkerSet.attachments`.
    """
    ms = markerset
    where = getattr(data, "path", None)
    idx, _ = ms.match(list(data.labels), where=where)
    pts = np.asarray(data.points, float)
    targets = np.where((idx >= 0)[None, :, None], pts[:, np.maximum(idx, 0)], np.nan)
    if smooth_hz:
        targets = lowpass_markers(targets, float(getattr(data, "rate", 0) or 0), smooth_hz)
    sel = sample_frames(targets, frames)
    if len(sel) == 0:
        raise MarkerSetError(where or ms.name, "no frame with at least 3 markers to calibrate on")
    nodes, local = ms.attachments(hand, right)
    bones = _joint_centre_bones(hand, ms, nodes, local, targets[sel])
    held = np.zeros(0, np.int64)
    if subject and not (len(bones) >= len(nodes) - 1 and bones):
        # skin markers: calibration frames and held-out frames come from different blocks
        sel, held = split_frames(targets, frames, held_out)
    tg = targets[sel]
    settings = settings or SolverSettings(iterations=15, damping=0.1)
    weights = np.array([m.weight for m in ms.markers])
    cal = Calibration(source=str(where or ""), frames_used=int(len(sel)), hand="right" if right else "left",
                      markerset=ms.name, hand_model=hand.name, source_sha256=_sha256_of(data))

    def residual(scale, bone_scales, offsets, positions=None, rotations=None, frames_sel=None, markers_sel=None):
        model = hand.scaled(scale, bone_scales)
        if positions:
            model = model.with_joint_positions(positions)
        if rotations:
            model = model.with_rest_rotations(rotations)
        n, l = ms.attachments(model, right, offsets, scale=scale)
        t = tg if frames_sel is None else tg[frames_sel]
        th, rep = fit_points(model, n, l, t, weights=weights, settings=settings, restarts=1)
        if markers_sel is None:
            return float(np.nanmedian(rep.rms_mm)), th, model, n, l
        e = np.linalg.norm(model.points(th, n[markers_sel], l[markers_sel]) - t[:, markers_sel], axis=-1)
        return float(np.nanmedian(np.sqrt(np.nanmean(e ** 2, axis=1))) * 1000.0), th, model, n, l

    if len(bones) >= len(nodes) - 1 and bones:
        # every bone measured: the model follows the data directly (joint-centre protocols); the
        # joints on the palm (finger bases) are then placed where the data has them in the hand frame
        cal.bone_scales = bones
        cal.method = "bone lengths from joint centres"
        palm = [i for i, n in enumerate(nodes) if hand.parents[n] == 0 and not np.any(local[i])]
        for _ in range(3):
            _, th, model, n, _ = residual(1.0, cal.bone_scales, None, cal.joint_positions)
            G0 = model.node_frames(th)[:, 0]
            pos = {}
            for i in palm:
                loc = np.einsum("sji,sj->si", G0[:, :3, :3], tg[:, i] - G0[:, :3, 3])
                ok = np.isfinite(loc).all(1)
                if ok.sum() >= 3:
                    pos[hand.node_names[nodes[i]]] = np.median(loc[ok], axis=0)
            cal.joint_positions = pos
            # the bone scale of a palm joint is now part of its position
            cal.bone_scales = {k: v for k, v in bones.items() if k not in pos}
        cal.method += " + finger bases on the palm"
        if orient_bases:
            cal.joint_rotations = _orient_finger_bases(hand, nodes, local, palm, residual, cal)
            cal.method += " + finger base orientations"
    else:
        cal.scale = golden_section(lambda s: residual(s, {}, None)[0], *scale_range)
        cal.method = "hand scale by marker-IK residual"
        if subject:
            tg_static = None
            if static is not None:
                sidx, _ = ms.match(list(static.labels), where=getattr(static, "path", None))
                sp = np.asarray(static.points, float)
                st = np.where((sidx >= 0)[None, :, None], sp[:, np.maximum(sidx, 0)], np.nan)
                if smooth_hz:
                    st = lowpass_markers(st, float(getattr(static, "rate", 0) or 0), smooth_hz)
                tg_static = st[sample_frames(st, 30)]
                cal.static_source = str(getattr(static, "path", "") or "")
            plain = deepcopy(cal)
            if static is None and neutral:
                # no static trial: the trial's own open-hand frames, if it has any, fix the joints'
                # zeros that a marker on the last bone of a chain leaves to its place on the bone
                model0 = hand.scaled(cal.scale)
                n0, l0 = ms.attachments(model0, right, scale=cal.scale)
                at = neutral_frames(model0, n0, l0, targets, weights)
                if len(at):
                    tg_static, static_sd_deg = targets[at], NEUTRAL_SD_DEG
                    cal.static_source = f"{len(at)} neutral frames of the trial"
                    cal.method += f" + {len(at)} neutral frames as the flat hand"

            def fit_subject(c, tg_st, sd_deg):
                refine_subject(hand, ms, right, c.scale, tg, targets[held], weights, bone_sd=bone_sd,
                               offset_scale=offset_scale, data_sd_mm=data_sd_mm, iterations=iterations, cal=c,
                               tg_static=tg_st, static_posture=static_posture, static_sd_deg=sd_deg,
                               posture_prior=None if tg_st is not None else posture_prior,
                               prior_frames=prior_frames)
                h = c.held_out
                return c.overfit or bool(require_gain is not None and h["frames"]
                                         and not h["residual_mm"] < require_gain * h["scale_only_residual_mm"])

            failed = fit_subject(cal, tg_static, static_sd_deg)
            if failed and static is None and tg_static is not None:
                # open frames that are not flat enough (a spread hand) bend the subject: without them
                cal = plain
                failed = fit_subject(cal, None, static_sd_deg)
            h = cal.held_out
            if failed:
                # the figures are the held-out check's (kept with the fallback, :func:`held_out_line`)
                why = ("it does not generalise" if cal.overfit else
                       f"its held-out median marker residual is not below {require_gain:g}× the hand scale alone's")
                kept = scale_only(cal)
                kept.warnings = [w for w in cal.warnings]
                kept.method += f" (bone and marker fit not used: {why})"
                kept.held_out = h
                cal = kept
    flagged = [i for i, m in enumerate(ms.markers) if m.calibrate_offset and idx[i] >= 0]
    if flagged and offset_iterations and not cal.offsets:
        offsets = None
        for _ in range(offset_iterations):
            _, th, model, n, l = residual(cal.scale, cal.bone_scales, offsets, cal.joint_positions)
            G = model.node_frames(th)  # (S, N, 4, 4)
            offsets = dict(offsets or {})
            for i in flagged:
                Gi = G[:, n[i]]
                loc = np.einsum("sji,sj->si", Gi[:, :3, :3], tg[:, i] - Gi[:, :3, 3])
                ok = np.isfinite(loc).all(1)
                if ok.sum() >= 3:
                    offsets[ms.markers[i].label] = np.median(loc[ok], axis=0)
        cal.offsets = offsets
        cal.method += " + marker offsets"
    cal.median_residual_mm = residual(cal.scale, cal.bone_scales, cal.offsets or None, cal.joint_positions,
                                      cal.joint_rotations)[0]
    rate = float(getattr(data, "rate", 0) or 0)
    if smooth_hz and smooth_hz < rate / 2:
        cal.method += f" (markers low-passed at {smooth_hz:g} Hz)"
    return cal


def held_out_line(h: dict) -> str:
    """The held-out check in words, every figure the median marker residual (the median over frames of
    a frame's RMS marker distance, the conversion table's "med mm"): both hands on the held-out frames
    and the calibrated hand on its fitted frames.

    >>> held_out_line({"frames": 50, "train_frames": 150, "residual_mm": 0.42, "train_residual_mm": 0.17,
    ...                "scale_only_residual_mm": 3.3})
    'median marker residual on 50 held-out frames 0.42 mm calibrated, 3.30 mm hand scale only (0.17 mm on the 150 fitted frames)'
    """
    return (f"median marker residual on {h['frames']} held-out frames {h['residual_mm']:.2f} mm calibrated, "
            f"{h['scale_only_residual_mm']:.2f} mm hand scale only ({h['train_residual_mm']:.2f} mm on the "
            f"{h['train_frames']} fitted frames)")


def scale_only(cal: Calibration) -> Calibration:
    """The hand-scale part of a skin-marker calibration (the fallback when the full one overfits)."""
    return Calibration(scale=cal.scale, frames_used=cal.frames_used, method="hand scale by marker-IK residual",
                       source=cal.source, source_sha256=cal.source_sha256, hand=cal.hand, markerset=cal.markerset,
                       hand_model=cal.hand_model, median_residual_mm=cal.held_out.get("scale_only_train_residual_mm",
                                                                                       cal.median_residual_mm),
                       warnings=list(cal.warnings))


def _sha256_of(data) -> str:

    p = getattr(data, "path", None)
    if p and Path(p).is_file():

        return sha256_file(p)
    pts = np.ascontiguousarray(np.asarray(data.points, float))
    return hashlib.sha256(pts.tobytes()).hexdigest()


def golden_section(f, lo, hi, iterations=14):
    g = (np.sqrt(5) - 1) / 2
    a, b = lo, hi
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(iterations):
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = f(d)
    return float((a + b) / 2)


# ------------------------------------------------------------------------------------------ files
def save_calibration(cal: Calibration, path, *, overwrite=False):
    """Write a subject calibration (YAML, ``data_schema/subject-calibration.schema.json``); atomic,
    never overwrites unless asked."""

    doc = {"schema_version": CALIBRATION_VERSION, "kind": "subject-calibration", **cal.to_dict()}
    problem = schema_errors(doc, "subject-calibration")
    if problem:  # a bug here, not the user's input
        raise SynergyError(path, f"calibration does not match its schema: {problem}")
    return atomic_write_text(path, yaml.safe_dump(doc, sort_keys=False, allow_unicode=True), overwrite=overwrite)


def load_calibration(path) -> Calibration:
    """Read a subject calibration written by :func:`save_calibration` (validated)."""

    doc = load_yaml(path, SynergyError)
    if not isinstance(doc, dict):
        raise SynergyError(path, "not a subject calibration (top level must be a mapping)")
    problem = schema_errors(doc, "subject-calibration")
    if problem:
        raise SynergyError(path, problem)
    d = {k: v for k, v in doc.items() if k not in ("schema_version", "kind")}
    d["offsets"] = {k: np.asarray(v, float) for k, v in d.get("offsets", {}).items()}
    d["joint_positions"] = {k: np.asarray(v, float) for k, v in d.get("joint_positions", {}).items()}
    return Calibration.from_dict(d)
