"""The shared damped Gauss-Newton IK solver (paper §IV-A/B, §V).

One solver serves marker IK (fixed correspondences) and ICP tracking (closest-point correspondences
re-found by the caller). Each Gauss-Newton step solves ``(JᵀW²J + D) δ = JᵀW²e`` in the coordinates
α of a :class:`~handmodel.subspace.Subspace` (``J_PC = J M``), with selective damping ``D`` (pose
damping on global-pose coordinates, ``damping`` on the rest), Chan–Dubey joint-limit damping,
an active set at the limits (a coordinate at its bound whose descent direction points outwards is
left out of that step's normal equations: :func:`handmodel._solver_kernels.freeze_at_limits`) and
clamping, and step halving until the energy drops. A schedule runs stages of growing subspaces
(hierarchical optimisation). Residuals are in millimetres, so damping values match the paper
(λ = 1) and the original code (λ = 5, applied squared).

Examples
--------
>>> import numpy as np
>>> from handmodel import HandModel
>>> hand = HandModel.load()
>>> truth = hand.zero(); truth[7] = -0.6                        # thumb CMC flexion
>>> theta, rep = fit_keypoints(hand, hand.keypoints(truth), theta0=hand.zero())
>>> bool(abs(theta[7] + 0.6) < 1e-6)
True
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import _solver_kernels as K
from .errors import SolverError
from .chain import ROTATION, TRANSLATION
from .rigid import horn, matrix_to_euler
from .subspace import Subspace


@dataclass
class SolverSettings:
    """Gauss-Newton settings (every field is exposed on the CLIs that use the solver).

    ``damping`` is λ on posture coordinates (paper: 1; original code: 25 = 5²), ``pose_damping`` the
    value on global-pose coordinates (paper: 0). ``damping_vector`` overrides both with one value per
    coordinate of the full space (ignored in reduced stages).
    """

    iterations: int = 10
    damping: float = 1.0
    pose_damping: float = 0.0
    damping_vector: np.ndarray | None = None
    joint_limit_avoidance: bool = True
    clamp: bool = True
    clamp_margin: float = 1e-4
    max_halvings: int = 10
    tol: float = 1e-12
    min_points: int = 1

    @classmethod
    def paper(cls, **kw) -> "SolverSettings":
        """The paper's values: λ = 1 on posture, 0 on pose, 5 GN iterations."""
        return cls(**{"iterations": 5, "damping": 1.0, "pose_damping": 0.0, **kw})


@dataclass
class SolveReport:
    """What a solve did: per frame GN iterations, final energy (mm², ½Σw²r²), RMS residual (mm),
    clamp events, DoFs at a limit, and the energy trace (NaN-padded)."""

    iterations: np.ndarray
    energy: np.ndarray
    rms_mm: np.ndarray
    clamps: np.ndarray
    at_limit: np.ndarray
    trace: np.ndarray
    stages: list = field(default_factory=list)

    def summary(self) -> dict:
        ok = self.iterations >= 0
        return {"frames": int(self.iterations.size), "solved": int(ok.sum()),
                "mean_iterations": float(self.iterations[ok].mean()) if ok.any() else float("nan"),
                "median_rms_mm": float(np.nanmedian(self.rms_mm)) if ok.any() else float("nan")}


def _stage_arrays(hand, stages, settings: SolverSettings):
    if not stages:
        raise SolverError("schedule", "empty schedule")
    n = hand.n_dofs
    S = len(stages)
    mmax = max(sp.dim for sp, _ in stages)
    st_M = np.zeros((S, n, mmax))
    st_mu = np.zeros((S, n))
    st_m = np.zeros(S, np.int64)
    st_lo = np.full((S, mmax), -np.inf)
    st_hi = np.full((S, mmax), np.inf)
    st_damp = np.zeros((S, mmax))
    st_iters = np.zeros(S, np.int64)
    st_ident = np.zeros(S, np.bool_)
    for s, (sp, iters) in enumerate(stages):
        if sp.M.shape[0] != n:
            raise SolverError("schedule", f"stage {s}: subspace has {sp.M.shape[0]} rows, model has {n} DoFs")
        m = sp.dim
        st_M[s, :, :m] = sp.M
        st_mu[s] = sp.mu
        st_m[s] = m
        st_lo[s, :m] = sp.lo
        st_hi[s, :m] = sp.hi
        if settings.damping_vector is not None and sp.is_identity:
            st_damp[s, :m] = np.asarray(settings.damping_vector, float)
        else:
            st_damp[s, :m] = np.where(sp.pose, settings.pose_damping, settings.damping)
        st_iters[s] = int(iters)
        st_ident[s] = sp.is_identity
    return st_M, st_mu, st_m, st_lo, st_hi, st_damp, st_iters, st_ident


def normalise_schedule(hand, subspace=None, schedule=None, iterations=10):
    """A list of ``(Subspace, iterations)`` from the user's ``subspace`` / ``schedule`` arguments."""
    if schedule is not None:
        if subspace is not None:
            raise SolverError("schedule", "give either a subspace or a schedule, not both")
        out = []
        for st in schedule:
            sp, it = (st if isinstance(st, tuple) else (st, iterations))
            out.append((Subspace.full(hand) if sp is None else sp, int(it)))
        return out
    return [(Subspace.full(hand) if subspace is None else subspace, int(iterations))]


def solve(hand, theta0, nodes, local, targets, *, weights=None, normals=None, subspace=None, schedule=None,
          settings: SolverSettings | None = None, warm_start: bool = False):
    """Fit θ so that points attached to the model reach their targets.

    Parameters
    ----------
    hand : HandModel
    theta0 : array (n,) or (F, n)
        Start values (one per frame, or one for all frames).
    nodes : int array (P,)
        Node that each point rides on.
    local : array (P, 3)
        Point offsets in the node frames (metres).
    targets : array (P, 3) or (F, P, 3)
        Target positions in metres; NaN rows are missing points.
    weights : array (P,) or (F, P), optional
    normals : array like ``targets``, optional
        Unit normals for point-to-plane terms (zero rows stay point-to-point).
    subspace, schedule
        A :class:`Subspace` for a flat solve, or a list of ``(Subspace | None, iterations)`` stages.
    warm_start : bool
        Start each frame from the previous frame's result (sequences).

    Returns
    -------
    theta : ndarray (n,) or (F, n)
    report : SolveReport
    """
    settings = settings or SolverSettings()
    tg = np.asarray(targets, float)
    single = tg.ndim == 2
    tg = np.ascontiguousarray(tg[None] if single else tg)
    if tg.ndim != 3 or tg.shape[2] != 3:
        raise SolverError("targets", f"shape {np.shape(targets)}: expected (P, 3) or (F, P, 3)")
    F, P = tg.shape[:2]
    nodes = np.ascontiguousarray(np.asarray(nodes, np.int64))
    local = np.ascontiguousarray(np.asarray(local, float).reshape(-1, 3))
    if nodes.shape != (P,) or local.shape != (P, 3):
        raise SolverError("correspondences", f"{nodes.shape} nodes / {local.shape} offsets for {P} targets")
    if P and (nodes.min() < 0 or nodes.max() >= hand.n_nodes):
        raise SolverError("correspondences", "node index out of range")
    th0 = hand.check_theta(theta0)
    th0 = np.ascontiguousarray(np.broadcast_to(th0, (F, hand.n_dofs)), dtype=float)
    if weights is None:
        w = np.ones((F, P))
    else:
        w = np.asarray(weights, float)
        w = np.ascontiguousarray(np.broadcast_to(w if w.ndim == 2 or not single else w[None], (F, P)))
        if np.any(~np.isfinite(w)) or np.any(w < 0):
            raise SolverError("weights", "weights must be finite and non-negative")
    if normals is None:
        nr = np.zeros((0, P, 3))
    else:
        nr = np.asarray(normals, float)
        nr = np.ascontiguousarray(np.nan_to_num(nr[None] if single else nr))
        if nr.shape != tg.shape:
            raise SolverError("normals", f"shape {nr.shape} differs from targets {tg.shape}")
    stages = normalise_schedule(hand, subspace, schedule, settings.iterations)
    arrs = _stage_arrays(hand, stages, settings)
    total_iters = int(sum(it for _, it in stages))
    out = np.empty((F, hand.n_dofs))
    iters = np.empty(F, np.int64)
    clamps = np.empty(F, np.int64)
    energies = np.empty(F)
    traces = np.full((F, total_iters + 1), np.nan)
    K.solve_sequence(th0, bool(warm_start), *hand.kernel_args(), nodes, local, tg, w, nr,
                     int(settings.min_points), *arrs, int(settings.max_halvings), float(settings.tol),
                     bool(settings.joint_limit_avoidance), bool(settings.clamp), float(settings.clamp_margin),
                     out, iters, clamps, energies, traces)
    valid_w = np.where(np.isnan(tg[..., 0]), 0.0, w)
    with np.errstate(invalid="ignore", divide="ignore"):
        # ½Σw²r² = E  →  weighted RMS distance (point-to-point) or plane distance (point-to-plane)
        rms = np.sqrt(2.0 * energies / (valid_w ** 2).sum(1))
    lim = hand.limits
    last_sp = stages[-1][0]
    if last_sp.is_identity:
        tol_l = 2 * settings.clamp_margin + 1e-9
        at_lim = (np.abs(out - last_sp.lo) <= tol_l) | (np.abs(out - last_sp.hi) <= tol_l)
    else:
        at_lim = (out < lim[:, 0] - 1e-9) | (out > lim[:, 1] + 1e-9)
    at_lim &= np.isfinite(out)
    rep = SolveReport(iterations=iters, energy=energies, rms_mm=rms, clamps=clamps, at_limit=at_lim, trace=traces,
                      stages=[(sp.label, it) for sp, it in stages])
    if single:
        return out[0], rep
    return out, rep


# ---------------------------------------------------------------------------------- keypoints
def rigid_pose_from_keypoints(hand, targets, posture=None):
    """Global pose aligning the model's keypoints at ``posture`` to ``targets`` (Horn), batched.

    ``targets`` is ``(..., n_nodes, 3)`` with NaN for missing keypoints; see :func:`rigid_pose`.
    """
    return rigid_pose(hand, np.arange(hand.n_nodes), np.zeros((hand.n_nodes, 3)), targets, posture)


def rigid_pose(hand, nodes, local, targets, posture=None):
    """Global pose aligning attached points of the model at ``posture`` to ``targets`` (Horn), batched.

    Uses the points that do not depend on the posture (on the root, or at the origin of one of its
    children, e.g. the wrist and the finger bases) where at least three are present in a frame,
    else every present point. Returns full θ ``(..., n_dofs)`` with the given posture (default zeros).
    """
    _check_pose_layout(hand)
    nodes = np.asarray(nodes, np.int64)
    local = np.asarray(local, float).reshape(-1, 3)
    tg = np.asarray(targets, float)
    lead = tg.shape[:-2]
    theta = np.zeros(lead + (hand.n_dofs,))
    if posture is not None:
        theta[..., ~hand.pose_mask] = posture
    present = ~np.isnan(tg).any(-1)
    par = hand.parents[nodes]
    rigid = (par < 0) | ((par == 0) & (np.abs(local).sum(1) == 0))
    use = present & rigid
    use = np.where((use.sum(-1) >= 3)[..., None], use, present)
    if np.any(use.sum(-1) < 3):
        raise SolverError("targets", f"{int(present.sum(-1).min())} points present in a frame: at least 3 "
                                     "are needed to place the hand")
    model_pts = hand.points(theta, nodes, local)  # pose zero: hand frame
    R, t = horn(model_pts, np.nan_to_num(tg), use.astype(float))
    theta[..., :3] = t
    theta[..., 3:6] = matrix_to_euler(R)
    return theta


def _check_pose_layout(hand):
    root = hand.dof_idx[hand.dof_ptr[0]:hand.dof_ptr[1]]
    ok = len(root) == 6 and list(root) == list(range(6))
    if ok:
        exp_t = [TRANSLATION] * 3 + [ROTATION] * 3
        ok = list(hand.dof_types[:6]) == exp_t and np.allclose(hand.dof_axes[:6], np.vstack([np.eye(3), np.eye(3)]))
    ok = ok and np.allclose(hand.rest[0], np.eye(4))
    if not ok:
        raise SolverError(hand.path, "rigid initialisation needs the root joint to carry tx ty tz rx ry rz first")


def fit_keypoints(hand, targets, theta0=None, *, subspace=None, schedule=None, settings: SolverSettings | None = None,
                  weights=None, warm_start: bool = False, restarts: int = 3, restart_rms_mm: float = 0.5):
    """Fit the model to 3-D keypoints (``(..., 21, 3)`` metres, NaN = missing).

    Without ``theta0`` each frame starts from the flat hand (the subspace mean posture when a
    subspace or schedule is given) placed rigidly on the keypoints (Horn). Frames whose RMS residual
    stays above ``restart_rms_mm`` (a local minimum, typical when keypoints are missing) are solved
    again from up to ``restarts`` other postures (flexed part-way to the limits, starting from the
    first solution's global pose) and the lowest-energy result is kept.
    Returns ``(theta, report)`` with θ of shape ``(..., n_dofs)``.
    """
    tg = np.asarray(targets, float)
    if tg.ndim < 2 or tg.shape[-2:] != (hand.n_nodes, 3):
        raise SolverError("targets", f"shape {tg.shape}: expected (..., {hand.n_nodes}, 3) keypoints")
    return fit_points(hand, np.arange(hand.n_nodes), np.zeros((hand.n_nodes, 3)), tg, theta0, subspace=subspace,
                      schedule=schedule, settings=settings, weights=weights, warm_start=warm_start,
                      restarts=restarts, restart_rms_mm=restart_rms_mm)


def fit_points(hand, nodes, local, targets, theta0=None, *, subspace=None, schedule=None,
               settings: SolverSettings | None = None, weights=None, warm_start: bool = False, restarts: int = 3,
               restart_rms_mm: float = 0.5):
    """Fit the model to target positions of points attached to its nodes (markers, keypoints).

    ``targets`` is ``(..., P, 3)`` metres with NaN for missing points. Without ``theta0`` frames start
    from the flat hand (or the subspace mean) placed by :func:`rigid_pose`; with ``warm_start`` a
    sequence runs frame to frame from the first frame's start. Frames left with an RMS residual above
    ``restart_rms_mm`` are re-solved from their rigid placement with the flat and up to ``restarts``
    part-flexed postures; the lowest energy wins. Returns ``(theta (..., n_dofs), SolveReport)``.
    """
    settings = settings or SolverSettings(iterations=30, damping=0.1)
    nodes = np.asarray(nodes, np.int64)
    local = np.asarray(local, float).reshape(-1, 3)
    tg = np.asarray(targets, float)
    P = len(nodes)
    if tg.ndim < 2 or tg.shape[-2:] != (P, 3):
        raise SolverError("targets", f"shape {tg.shape}: expected (..., {P}, 3) for {P} points")
    lead = tg.shape[:-2]
    flat = tg.reshape(-1, P, 3)
    base = None
    if schedule is not None:
        base = schedule[0][0] if isinstance(schedule[0], tuple) else schedule[0]
    elif subspace is not None:
        base = subspace
    posture = None if base is None else base.mu[~hand.pose_mask]
    enough = (~np.isnan(flat[..., 0])).sum(-1) >= max(3, settings.min_points)
    if theta0 is None:
        th0 = np.zeros((len(flat), hand.n_dofs))
        if warm_start:
            first = np.flatnonzero(enough)
            if first.size:
                th0[:] = rigid_pose(hand, nodes, local, flat[first[0]], posture)
        elif enough.any():
            th0[enough] = rigid_pose(hand, nodes, local, flat[enough], posture)
    else:
        th0 = np.broadcast_to(hand.check_theta(theta0), lead + (hand.n_dofs,)).reshape(-1, hand.n_dofs)
    w = None if weights is None else np.broadcast_to(np.asarray(weights, float), lead + (P,)).reshape(-1, P)
    run = SolverSettings(**{**settings.__dict__, "min_points": max(3, settings.min_points)})
    theta, rep = solve(hand, th0, nodes, local, flat, weights=w, subspace=subspace, schedule=schedule,
                       settings=run, warm_start=warm_start)
    redo = np.flatnonzero((rep.rms_mm > restart_rms_mm) & enough) if restarts else np.zeros(0, int)
    if redo.size:
        lim = np.where(np.isfinite(hand.limits), hand.limits, 0.0)
        post = ~hand.pose_mask
        placed = rigid_pose(hand, nodes, local, flat[redo], posture)
        for frac in (0.0, 0.5, 0.25, 0.75)[: restarts + 1]:
            start = placed.copy()
            if frac:
                start[:, post] = frac * np.minimum(lim[post, 0], 0.0)
            th_r, rep_r = solve(hand, start, nodes, local, flat[redo], weights=None if w is None else w[redo],
                                subspace=subspace, schedule=schedule, settings=run)
            better = rep_r.energy < rep.energy[redo]
            k = redo[better]
            theta[k] = th_r[better]
            for name in ("iterations", "energy", "rms_mm", "clamps", "at_limit", "trace"):
                getattr(rep, name)[k] = getattr(rep_r, name)[better]
            still = rep.rms_mm[redo] > restart_rms_mm
            redo, placed = redo[still], placed[still]
            if not redo.size:
                break
    return theta.reshape(lead + (hand.n_dofs,)), rep
