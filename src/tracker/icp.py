"""Pipeline stage ``icp``: one ICP fit of the hand to a point cloud.

A fit is ``n_rigid`` rigid steps (Horn 1987: the whole hand moved, posture fixed), then one
non-rigid step per :class:`Stage` (paper §V: correspondences, then damped Gauss-Newton IK in that
stage's subspace). What differs between the paper's full, reduced and hierarchical modes is only the
list of stages, which the schedule builders below make; the parts of a fit are named arguments:

>>> from handmodel import HandModel
>>> from handmodel.subspace import Subspace
>>> hand = HandModel.load()
>>> full = Subspace.full(hand, hand.limits)
>>> [s.entry for s in tracking_schedule("full", 4, full)]
['none', 'none', 'none', 'none']
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from handmodel.rigid import euler_to_matrix, horn, matrix_to_euler
from handmodel.solver import SolverSettings, solve
from handmodel.subspace import Subspace

from .correspond import local_offsets, silhouette_pairs
from .errors import TrackerError


@dataclass
class IcpSettings:
    """Iterations and the estimation of one ICP fit.

    ``rigid_iterations`` + ``icp_iterations`` per tracked frame (the paper: 1 + 4), each non-rigid one
    ``gn_iterations`` Gauss-Newton steps (5) with damping ``damping`` on posture and ``pose_damping``
    on the global pose (λ for residuals in mm; the paper's 1 and 0). ``robust_mm``: Cauchy scale of the
    data-term weights (0 = plain least squares, the paper's). ``silhouette_weight``: the model→data
    term (0 = off, the paper's). ``point_to_plane``: point-to-plane data residuals. Reduced tracking:
    ``projected_steps`` last iterations with all DoF, projected onto the PCs (0 = the paper's α-only
    fit). Hierarchical tracking: ``coarse_iterations`` in the synergy subspace first.
    """

    rigid_iterations: int = 1
    icp_iterations: int = 4
    gn_iterations: int = 5
    damping: float = 1.0
    pose_damping: float = 0.0
    robust_mm: float = 8.0
    silhouette_weight: float = 1.0
    point_to_plane: bool = False
    projected_steps: int = 0
    coarse_iterations: int = 1

    def check(self):
        if self.icp_iterations < 0 or self.rigid_iterations < 0 or self.gn_iterations < 1:
            raise TrackerError("settings", "icp_iterations and rigid_iterations must be ≥ 0, gn_iterations ≥ 1")
        if self.projected_steps < 0 or self.robust_mm < 0 or self.silhouette_weight < 0:
            raise TrackerError("settings", "projected_steps, robust_mm and silhouette_weight must not be negative")

    def solver(self) -> SolverSettings:
        return SolverSettings(iterations=self.gn_iterations, damping=self.damping, pose_damping=self.pose_damping,
                              min_points=3)


@dataclass(frozen=True)
class Stage:
    """One non-rigid ICP iteration's parameter space.

    ``entry``: ``"none"`` (all DoF), ``"clamp"`` (θ is first moved into the subspace, inside its PC
    limits) or ``"through"`` (the same directions re-centred on θ, which keeps what was found outside
    the subspace). ``project``: after the step, θ is projected onto this subspace (reduced tracking's
    projected steps).
    """

    subspace: Subspace
    entry: str = "none"
    project: Subspace | None = None


MODES = ("full", "reduced", "hierarchical")


def tracking_schedule(mode, n, full, reduced=None, *, projected_steps=0, coarse_iterations=1) -> list[Stage]:
    """Stages of a tracked frame: ``full`` all DoF; ``reduced`` the synergy subspace (its last
    ``projected_steps`` with all DoF, projected onto it — never the first); ``hierarchical``
    ``coarse_iterations`` in the synergy subspace through θ, then all DoF."""
    if mode == "full":
        return [Stage(full)] * n
    if reduced is None:
        raise TrackerError("synergies", f"mode {mode!r} needs a synergy subspace")
    if mode == "reduced":
        first_projected = max(n - projected_steps, 1) if projected_steps else n
        return [Stage(full, project=reduced) if k >= first_projected else Stage(reduced, "clamp") for k in range(n)]
    if mode == "hierarchical":
        return [Stage(reduced, "through") if k < coarse_iterations else Stage(full) for k in range(n)]
    raise TrackerError("settings", f"mode must be one of {', '.join(MODES)}, got {mode!r}")


def search_schedule(mode, n, full, reduced=None, ladder=(), *, through=False) -> list[Stage]:
    """Stages of a fit without temporal prior: ``hierarchical`` spreads the ``ladder`` of growing
    subspaces (ending with all DoF) over the ``n`` iterations, early ones coarse; ``through`` re-centres
    them on θ (refining a start that already holds a posture) instead of clamping θ into them."""
    if mode == "full":
        return [Stage(full)] * n
    if mode == "reduced":
        if reduced is None:
            raise TrackerError("synergies", "mode 'reduced' needs a synergy subspace")
        return [Stage(reduced, "clamp")] * n
    if mode != "hierarchical":
        raise TrackerError("settings", f"mode must be one of {', '.join(MODES)}, got {mode!r}")
    ladder = list(ladder) or [full]
    entry = "through" if through else "clamp"
    out = []
    for k in range(n):
        sp = ladder[min(int(k * len(ladder) / max(n, 1)), len(ladder) - 1)]
        out.append(Stage(sp) if sp is full else Stage(sp, entry))
    return out


def clamp(subspace, theta) -> np.ndarray:
    """θ moved into ``subspace``: projected onto it, its coordinates clipped to the limits."""
    return subspace.to_theta(np.clip(subspace.to_alpha(theta), subspace.lo, subspace.hi))


def through(subspace, theta, pose_mask) -> Subspace:
    """The same synergy directions, but through θ (a refinement keeps what an earlier stage or frame
    found outside the subspace); the PC limits shift accordingly."""
    a = subspace.to_alpha(theta)
    mu = np.array(theta, float)
    mu[pose_mask] = 0.0
    # θ itself is always admitted: a posture outside the PC limits (rarer than any training posture)
    # must not be clamped back to them by the coarse step
    return Subspace(subspace.M, mu, np.minimum(subspace.lo - a, 0.0), np.maximum(subspace.hi - a, 0.0),
                    subspace.pose, label=subspace.label + " (through θ)")


def apply_rigid(theta, R, t) -> np.ndarray:
    """θ with the global pose pre-multiplied by the rigid motion x ↦ R x + t."""
    th = np.array(theta, float)
    Rp = euler_to_matrix(th[3:6])
    th[:3] = R @ th[:3] + t
    th[3:6] = matrix_to_euler(R @ Rp)
    return th


def rigid_step(theta, data_points, corr, weights=None) -> np.ndarray:
    """One rigid ICP update from valid correspondences; θ unchanged with fewer than 3 pairs."""
    v = corr.valid
    if v.sum() < 3:
        return np.array(theta, float)
    R, t = horn(corr.model[v], data_points[v], None if weights is None else weights[v])
    return apply_rigid(theta, R, t)


def cauchy_weights(distance_m, scale_mm) -> np.ndarray:
    """IRLS weights of the Cauchy loss: pairs far off (a finger the subspace cannot bend there, a
    wrong match) lose weight instead of dragging the global pose; ``scale_mm`` 0 = all ones."""
    d = np.asarray(distance_m, float)
    if not scale_mm:
        return np.ones(len(d))
    return 1.0 / np.sqrt(1.0 + (d * 1000.0 / scale_mm) ** 2)


def fit(hand, points, theta, stages, matcher, settings: IcpSettings | None = None, *, n_rigid=0, normals=None,
        samples=None, silhouette=None):
    """ICP: ``n_rigid`` rigid steps, then one damped Gauss-Newton IK per stage of ``stages``.

    Parameters
    ----------
    hand : HandModel
    points : (N, 3) data points, camera frame, metres
    theta : (n_dofs,) start
    stages : list of :class:`Stage` (see :func:`tracking_schedule`, :func:`search_schedule`)
    matcher : callable ``(theta, points, normals) -> Correspondences`` (:class:`tracker.correspond.Matcher`)
    settings : IcpSettings (estimation: robust weights, silhouette weight, point-to-plane, damping)
    normals : (N, 3) data normals or None (NaN rows: unknown)
    samples, silhouette : :class:`tracker.correspond.ModelSamples` and :class:`~tracker.correspond.Silhouette`
        for the model→data term (both or neither)

    Returns
    -------
    theta, Correspondences at the result
    """
    st = settings or IcpSettings()
    solver = st.solver()
    corr = None
    for _ in range(n_rigid):
        corr = matcher(theta, points, normals)
        theta = rigid_step(theta, points, corr)
    for stage in stages:
        corr = matcher(theta, points, normals)
        v = corr.valid
        if v.sum() < 3:
            break
        sp = stage.subspace
        if stage.entry == "through":
            sp = through(sp, theta, hand.pose_mask)
        elif stage.entry == "clamp":
            theta = clamp(sp, theta)
        nodes = corr.nodes[v]
        loc = local_offsets(hand, theta, nodes, corr.model[v])
        tg = points[v]
        w = cauchy_weights(corr.distance[v], st.robust_mm)
        plane = corr.normals[v] if st.point_to_plane else None
        if silhouette is not None and samples is not None and st.silhouette_weight > 0:
            sn, sl, stg = silhouette_pairs(samples, theta, silhouette)
            if len(sn):
                nodes, loc, tg = np.r_[nodes, sn], np.r_[loc, sl], np.r_[tg, stg]
                # weight per pair so the term counts like the data term per unit area
                w = np.r_[w, np.full(len(sn), st.silhouette_weight * np.sqrt(max(v.sum(), 1) / max(len(samples.nodes), 1)))]
                if plane is not None:
                    plane = np.r_[plane, np.zeros((len(sn), 3))]
        theta, _ = solve(hand, theta, nodes, loc, tg, weights=w, normals=plane, subspace=sp, settings=solver)
        if stage.project is not None:
            theta = clamp(stage.project, theta)
    corr = matcher(theta, points, normals)
    return theta, corr
