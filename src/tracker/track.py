"""Per-frame tracking: prediction → rigid ICP → non-rigid ICP-IK (full, reduced or hierarchical),
start from the segmented cloud, failure detection and re-initialisation.

The paper's defaults (§VI, FORMAT.md §5): 1 rigid + 4 non-rigid ICP iterations × 5 Gauss-Newton
steps, every 3rd pixel in x and y, pairs ≥ 50 mm rejected, λ = 1 on posture, 0 on pose.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from handmodel.solver import SolverSettings, solve
from handmodel.subspace import Subspace

from .correspond import CapsuleModel, MeshModel, ModelSamples, Silhouette, local_offsets, silhouette_pairs
from .errors import TrackerError
from .rigid import rigid_step

MODES = ("full", "reduced", "hierarchical")


@dataclass
class TrackerSettings:
    """Every knob of the tracker; ``TrackerSettings.paper()`` gives the paper's values."""

    mode: str = "full"
    rigid_iterations: int = 1
    icp_iterations: int = 4
    gn_iterations: int = 5
    stride: int = 3                    # every k-th pixel in x and y (the paper's "1/3 sampling" is 3) …
    target_points: int | None = 600    # … or, when set, the largest stride ≤ `stride` keeping this many points
    smooth: int = 1                    # edge-preserving depth smoothing radius (px) before sampling; 0 = off
    reject_mm: float = 50.0
    damping: float = 1.0
    pose_damping: float = 0.0
    prediction: float = 1.0            # share of the last frame's change added before fitting (0 = off)
    facing_only: bool = True
    point_to_plane: bool = False
    model: str = "capsules"            # or "mesh"
    n_pcs: int | None = None           # reduced/hierarchical: number of PCs …
    variance: float | None = 0.99      # … or the variance they must explain
    hierarchy: tuple = (1, 4)          # PC counts of the reduced stages before full DoF
    projected_steps: int = 0           # reduced tracking: last ICP iterations with all DoF, projected onto
                                       # the PCs (0 = the paper's α-only fit; 2: more accurate unoccluded)
    coarse_iterations: int = 1         # hierarchical tracking: ICP iterations in the synergy subspace first
    limits: str = "anatomical"         # joint limits: "anatomical" (synergy.angles), "data" (the bundle's joint
                                       # min/max, as the original with PCA on) or "model" (the model file's)
    lost_fit_mm: float = 12.0
    lost_rejected: float = 0.6
    min_points: int = 30
    init_icp_iterations: int = 12
    init_postures: int = 2             # single-frame fits start from the mean and ±σ along this many PCs
    finger_search: bool = True         # single-frame fits: finger-variant starts and finger-wise restarts
    finger_search_icp: int = 10        # … ICP iterations (all DoF, full cloud) for a finger's best restart
    max_points: int | None = None
    silhouette_weight: float = 1.0     # model→data term for model parts outside the silhouette (0 = paper)
    normal_agreement: float = 0.5      # with data normals: reject pairs whose normals' cosine is below this
    robust_mm: float = 8.0             # Cauchy scale (mm) for data-term weights; 0 = plain least squares (paper)

    @classmethod
    def paper(cls, **kw) -> "TrackerSettings":
        return cls(**kw)

    def check(self):
        if self.mode not in MODES:
            raise TrackerError("settings", f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if self.model not in ("capsules", "mesh"):
            raise TrackerError("settings", f"model must be 'capsules' or 'mesh', got {self.model!r}")
        if self.projected_steps < 0 or self.robust_mm < 0:
            raise TrackerError("settings", "projected_steps and robust_mm must not be negative")
        for k in ("icp_iterations", "gn_iterations", "stride"):
            if getattr(self, k) < (1 if k != "icp_iterations" else 0):
                raise TrackerError("settings", f"{k} must be positive")


@dataclass
class FrameResult:
    theta: np.ndarray
    status: str                 # tracked | lost | reinit
    fit_mm: float
    points_used: int
    points_in: int
    ms: float
    rejected_share: float = 0.0


class HandTracker:
    """Track one hand through a sequence of point clouds (camera frame, metres).

    Parameters
    ----------
    hand : HandModel
    settings : TrackerSettings
    synergies : a synergy bundle (``synergy.bundle.Bundle``) or ``None`` (full mode only)
    """

    def __init__(self, hand, settings: TrackerSettings | None = None, synergies=None):
        self.hand = hand
        self.settings = settings = settings or TrackerSettings()
        settings.check()
        if settings.mode != "full" and synergies is None:
            raise TrackerError("synergies", f"mode {settings.mode!r} needs a synergy bundle (--synergies)")
        self.synergies = synergies
        lim = np.array(hand.limits, float)
        if settings.limits == "anatomical":
            from synergy.angles import anatomical_limits

            lim = anatomical_limits(hand)
        elif settings.limits not in ("data", "model"):
            raise TrackerError("settings", f"limits must be anatomical, data or model, got {settings.limits!r}")
        if synergies is not None and settings.limits == "data":
            post = ~hand.pose_mask
            lim[post, 0] = synergies.model.joint_min_
            lim[post, 1] = synergies.model.joint_max_
        self.limits = lim
        self.full = Subspace.full(hand, lim)
        self.n_pcs = None
        if synergies is not None:
            m = synergies.model
            if settings.n_pcs is not None:
                l = int(settings.n_pcs)
            else:
                l = m.n_components_for(settings.variance if settings.variance else 0.99)
            if not 1 <= l <= m.all_components_.shape[0]:
                raise TrackerError("synergies", f"{l} PCs requested, the bundle has {m.all_components_.shape[0]}")
            self.n_pcs = l
            C, mu = m.all_components_, m.mean_
            self._pc = lambda k: Subspace.from_synergies(hand, C, mu, m.pc_min_, m.pc_max_, n_components=k)
            self.reduced = self._pc(l)
        self.correspond = CapsuleModel(hand) if settings.model == "capsules" else MeshModel(hand)
        self.samples = ModelSamples(hand) if settings.silhouette_weight > 0 else None
        self.finger_shapes = self._make_finger_shapes()
        self.solver = SolverSettings(iterations=settings.gn_iterations, damping=settings.damping,
                                     pose_damping=settings.pose_damping, min_points=3)
        self.reset()

    # --------------------------------------------------------------------------------------------
    def reset(self):
        self.last_good = None
        self.theta = None
        self.prev = None
        self.lost = True

    def _through(self, sp, theta):
        """The same synergy directions, but through the current θ (a refinement that keeps what the
        previous stage or frame found outside the subspace); PC limits shift accordingly."""
        from handmodel.subspace import Subspace

        a = sp.to_alpha(theta)
        mu = np.array(theta, float)
        mu[self.hand.pose_mask] = 0.0
        # θ itself is always allowed: a posture outside the PC limits (rarer than any training posture)
        # must not be clamped back to them by the coarse step
        return Subspace(sp.M, mu, np.minimum(sp.lo - a, 0.0), np.maximum(sp.hi - a, 0.0), sp.pose,
                        label=sp.label + " (through θ)")

    def _stage(self, k, n_stages, mode, tracking=False):
        if mode == "full":
            return self.full
        if mode == "reduced":
            return self.reduced
        if tracking:
            # tracking: `coarse_iterations` in the synergy subspace (through θ), then all DoF
            return self.reduced if k < self.settings.coarse_iterations else self.full
        steps = [s for s in self.settings.hierarchy if s < self.n_pcs] + [self.n_pcs]
        stages = [self._pc(s) for s in steps] + [self.full]
        # spread the stages over the ICP iterations: early iterations coarse, the last one(s) full DoF
        i = min(int(k * len(stages) / max(n_stages, 1)), len(stages) - 1)
        return stages[i]

    def _corr(self, theta, points, normals):
        st = self.settings
        corr = self.correspond(theta, points, reject=st.reject_mm / 1000.0, facing_only=st.facing_only)
        if normals is not None and st.normal_agreement > -1:
            # a data point on a surface facing another way than the model's is a wrong pair
            cos = np.einsum("ij,ij->i", normals, corr.normals)
            corr.valid &= ~(cos < st.normal_agreement)  # NaN (unknown normal) keeps the pair
        return corr

    def _icp(self, theta, points, n_rigid, n_icp, mode, obs=None, normals=None, refine=False, tracking=False):
        """Rigid then non-rigid ICP. ``refine``: hierarchical stages pass through the current θ
        (tracking) instead of through the synergy mean (single-frame fits)."""
        st = self.settings
        corr = None
        for _ in range(n_rigid):
            corr = self._corr(theta, points, normals)
            theta = rigid_step(theta, points, corr)
        for k in range(n_icp):
            corr = self._corr(theta, points, normals)
            v = corr.valid
            if v.sum() < 3:
                break
            sp = self._stage(k, n_icp, mode, tracking)
            # reduced tracking, last `projected_steps` iterations: all DoF, the result projected onto the PCs
            # in joint-angle space (the closest subspace posture, which α-only fitting cannot reach)
            project = mode == "reduced" and tracking and k >= max(n_icp - st.projected_steps, 1)
            if project:
                sp = self.full
            if sp is not self.full:
                if mode == "hierarchical" and refine:
                    sp = self._through(sp, theta)
                else:
                    theta = sp.to_theta(np.clip(sp.to_alpha(theta), sp.lo, sp.hi))
            nodes = corr.nodes[v]
            loc = local_offsets(self.hand, theta, nodes, corr.model[v])
            tg = points[v]
            w = np.ones(len(nodes))
            if st.robust_mm > 0:
                # Cauchy IRLS: pairs far off (a finger the subspace cannot bend there, a wrong match)
                # lose weight instead of dragging the global pose
                w = 1.0 / np.sqrt(1.0 + (corr.distance[v] * 1000.0 / st.robust_mm) ** 2)
            normals = corr.normals[v] if st.point_to_plane else None
            if obs is not None and self.samples is not None:
                sn, sl, st_ = silhouette_pairs(self.samples, theta, obs)
                if len(sn):
                    nodes, loc, tg = np.r_[nodes, sn], np.r_[loc, sl], np.r_[tg, st_]
                    # weight per pair so the term counts like the data term per unit area
                    w = np.r_[w, np.full(len(sn), st.silhouette_weight * np.sqrt(max(v.sum(), 1) / max(len(self.samples.nodes), 1)))]
                    if normals is not None:
                        normals = np.r_[normals, np.zeros((len(sn), 3))]
            theta, _ = solve(self.hand, theta, nodes, loc, tg, weights=w, normals=normals, subspace=sp,
                             settings=self.solver)
            if project:
                r = self.reduced
                theta = r.to_theta(np.clip(r.to_alpha(theta), r.lo, r.hi))
        corr = self._corr(theta, points, normals)
        return theta, corr

    def initial_pose(self, points):
        """Candidate starts from the cloud: the model's surface centroid on the data centroid, its
        principal axes on the data's (fingers along the main axis; the four sign choices)."""
        from handmodel.geometry import surface_samples
        from handmodel.rigid import matrix_to_euler

        base = np.zeros(self.hand.n_dofs)
        if self.synergies is not None:
            base[~self.hand.pose_mask] = self.synergies.model.mean_
        S, _, N = surface_samples(self.hand, base, spacing=0.004)
        # what a camera in front of the palm sees: the palm-side half
        ms = S[N[:, 2] < 0]
        mc = ms.mean(0)
        dc = points.mean(0)
        _, _, Vm = np.linalg.svd(ms - mc, full_matrices=False)
        _, _, Vd = np.linalg.svd(points - dc, full_matrices=False)
        from scipy.spatial.transform import Rotation

        cands = []
        for s1 in (1, -1):
            for s3 in (1, -1):
                A = np.stack([Vm[0], np.cross(Vm[2], Vm[0]), Vm[2]], 1)
                d1, d3 = s1 * Vd[0], s3 * Vd[2]
                B = np.stack([d1, np.cross(d3, d1), d3], 1)
                # a curled hand's main axis need not be the fingers': also roll about it
                for roll in (0.0, 45.0, -45.0, 90.0, -90.0):
                    R = Rotation.from_rotvec(np.radians(roll) * d1).as_matrix() @ B @ A.T
                    th = base.copy()
                    th[3:6] = matrix_to_euler(R)
                    th[:3] = dc - R @ mc
                    cands.append(th)
        return cands

    def _score(self, theta, corr, obs):
        """Lower is better: mean data→model distance (mm) plus the share of front-facing model
        samples outside the silhouette (× 20 mm) and of rejected data points (× 100 mm)."""
        score = corr.fit_error_mm() + 100.0 * (1.0 - corr.valid.mean())
        if obs is not None and self.samples is not None and not obs.empty:
            n_out = len(silhouette_pairs(self.samples, theta, obs)[0])
            score += 20.0 * n_out / max(len(self.samples.nodes), 1)
        return score

    def posture_grid(self):
        """A grid of start postures over the first three synergies (PC1 at −2…+2 σ, PC2 and PC3 at
        −1, 0, +1 σ), inside the PC limits: the search space of single-frame fits."""
        m = self.synergies.model
        sd = np.sqrt(m.all_explained_variance_)
        out = []
        for a1 in (-2.0, -1.0, 0.0, 1.0, 2.0):
            for a2 in (-1.0, 0.0, 1.0):
                for a3 in (-1.0, 0.0, 1.0):
                    a = np.clip(np.array([a1 * sd[0], a2 * sd[1], a3 * sd[2]]), m.pc_min_[:3], m.pc_max_[:3])
                    out.append(m.mean_ + a @ m.all_components_[:3])
        return out

    def posture_candidates(self, k=None):
        """Start postures for single-frame fits: the synergy mean and ±σ along the first PCs."""
        post = ~self.hand.pose_mask
        if self.synergies is None:
            return [np.zeros(int(post.sum()))]
        m = self.synergies.model
        sd = np.sqrt(m.all_explained_variance_)
        out = [m.mean_.copy()]
        for pc, amp in ((0, 1.5), (1, 1.2), (2, 1.2))[: (k if k is not None else self.settings.init_postures)]:
            for sgn in (1, -1):
                out.append(m.mean_ + sgn * amp * sd[pc] * m.all_components_[pc])
        return out

    @staticmethod
    def _diverse(scored, k, min_deg=60.0):
        """The best ``k`` of (score, θ) sorted by score whose global rotations differ pairwise by at
        least ``min_deg`` (so a palm-facing and a back-facing placement both go on when the cloud
        alone cannot tell them apart), filled up with the next best if fewer are that different."""
        from handmodel.rigid import euler_to_matrix

        picked, Rs = [], []
        for _, th in scored:
            R = euler_to_matrix(th[3:6])
            if all(np.degrees(np.arccos(np.clip((np.trace(R @ Q.T) - 1) / 2, -1, 1))) >= min_deg for Q in Rs):
                picked.append(th)
                Rs.append(R)
                if len(picked) == k:
                    return picked
        rest = [th for _, th in scored if not any(th is p for p in picked)]
        return picked + rest[: k - len(picked)]

    def fit_single_frame(self, points, theta0=None, mode=None, obs=None, postures=None, normals=None, extra=(),
                         search=True):
        """Fit one frame without temporal prior: from ``theta0``'s global pose (or candidate poses
        from the cloud's principal axes) and several synergy postures, each refined by ICP (the
        hierarchical schedule by default when synergies exist); the best-scoring fit wins."""
        st = self.settings
        mode = mode or ("hierarchical" if self.synergies is not None else "full")
        sub = slice(None, None, max(1, len(points) // 800))
        nsub = None if normals is None else normals[sub]
        post = ~self.hand.pose_mask
        if theta0 is not None:
            poses = [np.array(theta0, float)]
        else:
            # many candidate placements, each briefly fitted; the best three go on
            quick = []
            for pose in self.initial_pose(points):
                for p in self.posture_candidates(1):
                    th = pose.copy()
                    th[post] = p
                    th, corr = self._icp(th, points[sub], 2, 4, mode, obs, nsub)
                    quick.append((self._score(th, corr, obs), th))
            quick.sort(key=lambda x: x[0])
            poses = self._diverse(quick, 3)
        posts = self.posture_candidates() if postures is None else postures
        post = ~self.hand.pose_mask
        starts = []
        for pose in poses:
            for p in posts:
                th = pose.copy()
                if theta0 is None or len(posts) > 1:
                    th[post] = p
                starts.append((th, False))
        # e.g. the last good estimate before the hand was lost: refined through itself (not re-projected
        # onto the synergy mean's subspaces), as it is and re-placed on the cloud
        for th in extra:
            starts.append((np.array(th, float), True))
            moved = np.array(th, float)
            centre = (self.hand.keypoints(moved)[[0, 5, 9, 13, 17]]).mean(0)
            moved[:3] += points.mean(0) - centre
            starts.append((moved, True))
        if search and self.synergies is not None and postures is None:
            # coarse search: short fits from a synergy grid on a thinned cloud, the best few refined fully
            coarse = []
            for pose in poses:
                for p in self.posture_grid():
                    th = pose.copy()
                    th[post] = p
                    th, corr = self._icp(th, points[sub], 1, 4, "reduced" if mode != "full" else "full", obs, nsub)
                    coarse.append((self._score(th, corr, obs), th))
                if st.finger_search:
                    # and the synergy mean with one finger in another shape (what no synergy posture holds)
                    at_mean = pose.copy()
                    at_mean[post] = self.synergies.model.mean_
                    for th in self.finger_variants(at_mean):
                        th, corr = self._icp(th, points[sub], 1, 4, "full", obs, nsub)
                        coarse.append((self._score(th, corr, obs), th))
            coarse.sort(key=lambda x: x[0])
            starts = [(th, True) for _, th in coarse[:3]] + starts
        best = None
        for th, refine in starts:
            th, corr = self._icp(th, points, 2, st.init_icp_iterations, mode, obs, normals, refine=refine)
            score = self._score(th, corr, obs)
            if best is None or score < best[0]:
                best = (score, th, corr)
        if search and st.finger_search:
            best = self._finger_search(best, points, obs, normals, sub)
        return best[1], best[2]

    # finger shapes for finger-wise restarts: flexion (°) of the first, second and third flexion joint
    # (MCP, PIP, DIP; for the thumb CMC, MCP, IP): straight, evenly curled, PIP-led curl (a finger
    # flexed alone, as in fingerfist), MCP-led bend, hook
    FINGER_SHAPES_DEG = ((5.0, 5.0, 5.0), (-25.0, -25.0, -25.0), (-55.0, -55.0, -55.0), (-85.0, -85.0, -85.0),
                         (-45.0, -100.0, -10.0), (-80.0, -20.0, -10.0), (0.0, -90.0, -60.0))

    def _make_finger_shapes(self):
        """Per finger (thumb … pinky): the θ indices of its flexion joints and FINGER_SHAPES_DEG as
        values for them, inside the joint limits — one row per shape."""
        names = list(self.hand.dof_names)
        lo, hi = self.limits[:, 0], self.limits[:, 1]
        out = []
        for f in ("thumb", "index", "middle", "ring", "pinky"):
            fi = np.array([i for i, n in enumerate(names) if n.startswith(f) and "flex" in n], np.int64)
            if fi.size:
                vals = np.radians([np.resize(shape, fi.size) for shape in self.FINGER_SHAPES_DEG])
                out.append((fi, np.clip(vals, lo[fi], hi[fi])))
        return out

    def finger_variants(self, theta, finger=None):
        """Copies of ``theta`` with one finger's flexion joints set to each finger shape, every finger
        in turn (or only ``finger``, an index into ``finger_shapes``), the rest unchanged."""
        out = []
        for k, (fi, vals) in enumerate(self.finger_shapes):
            if finger is None or finger == k:
                for v in vals:
                    th = np.array(theta, float)
                    th[fi] = v
                    out.append(th)
        return out

    def _finger_search(self, best, points, obs, normals, sub, sweeps=2):
        """Finger-wise restarts: synergies couple the fingers, so a finger flexed alone (a ring finger
        curled into the palm, a thumb tucked under) lies outside every start the synergy grid gives.
        Each finger in turn is set to a few shapes (the rest of the hand as found), refitted briefly with
        all DoF on a thinned cloud; the best is refitted on the full cloud and kept only when the
        whole-frame score improves. Repeated while a sweep improves something."""
        st = self.settings
        nsub = None if normals is None else normals[sub]
        score, theta, corr = best
        for _ in range(sweeps):
            improved = False
            for k, (fi, _) in enumerate(self.finger_shapes):
                tried = []
                for th in self.finger_variants(theta, k):
                    if np.max(np.abs(th[fi] - theta[fi])) < np.radians(12.0):
                        continue  # the finger has that shape already
                    th, c = self._icp(th, points[sub], 0, 4, "full", obs, nsub)
                    tried.append((self._score(th, c, obs), th))
                if not tried:
                    continue
                tried.sort(key=lambda x: x[0])
                th, c = self._icp(tried[0][1], points, 0, st.finger_search_icp, "full", obs, normals)
                s = self._score(th, c, obs)
                if s < score - 1e-3:
                    score, theta, corr, improved = s, th, c, True
            if not improved:
                break
        return score, theta, corr

    def track(self, observation, camera) -> FrameResult:
        """Track one :class:`tracker.observe.Observation`."""
        return self.step(observation.points, normals=observation.normals, mask=observation.mask,
                         depth=observation.depth, camera=camera)

    def step(self, points, *, normals=None, mask=None, depth=None, camera=None) -> FrameResult:
        """Track one frame's segmented points ``(N, 3)`` (camera frame, metres; NaN rows ignored).

        With the hand ``mask``, the ``depth`` image (metres) and the ``camera``, model parts that
        leave the silhouette are pulled back (``silhouette_weight``)."""
        obs = None if mask is None or camera is None or depth is None else Silhouette(mask, depth, camera)
        t0 = time.perf_counter()
        st = self.settings
        pts = np.asarray(points, float).reshape(-1, 3)
        keep = np.isfinite(pts).all(1)
        if st.max_points and keep.sum() > st.max_points:
            idx = np.flatnonzero(keep)
            keep[:] = False
            keep[idx[np.linspace(0, len(idx) - 1, st.max_points).astype(int)]] = True
        pts = pts[keep]
        # NaN normals (unknown) keep their pairs: the cosine test is skipped for them
        nrm = None if normals is None else np.asarray(normals, float).reshape(-1, 3)[keep]
        n_in = len(pts)
        if n_in < st.min_points:
            self.lost = True
            th = self.theta if self.theta is not None else np.full(self.hand.n_dofs, np.nan)
            return FrameResult(np.array(th, float), "lost", float("nan"), 0, n_in, (time.perf_counter() - t0) * 1e3, 1.0)
        if self.lost or self.theta is None:
            extra = () if self.last_good is None else (self.last_good,)
            theta, corr = self.fit_single_frame(pts, obs=obs, normals=nrm, extra=extra)
            status = "reinit"
            self.prev = None
        else:
            theta = self.theta.copy()
            if st.prediction and self.prev is not None:
                # constant-velocity prediction, except for the global rotation (as the original code)
                step = (self.theta - self.prev) * float(st.prediction)
                step[3:6] = 0.0
                if st.mode == "reduced":
                    # reduced: the posture moves along the synergies only (hierarchical mode predicts
                    # all DoF: motion outside the synergies — one finger alone — is real motion there)
                    post = ~self.hand.pose_mask
                    C = self.synergies.model.all_components_[: self.n_pcs]
                    step[post] = (step[post] @ C.T) @ C
                theta = theta + step
                post = ~self.hand.pose_mask
                theta[post] = np.clip(theta[post], self.limits[post, 0], self.limits[post, 1])
            theta, corr = self._icp(theta, pts, st.rigid_iterations, st.icp_iterations, st.mode, obs, nrm,
                                    refine=True, tracking=True)
            status = "tracked"
        fit = corr.fit_error_mm()
        rejected = 1.0 - corr.valid.mean() if len(pts) else 1.0
        ok = np.isfinite(fit) and fit <= st.lost_fit_mm and rejected <= st.lost_rejected
        if ok:
            self.prev, self.theta = (self.theta if status == "tracked" else None), theta
            self.last_good = theta
            self.lost = False
        else:
            self.lost = True
            status = "lost"
            self.theta = theta
            self.prev = None
        return FrameResult(theta, status, fit, corr.used, n_in, (time.perf_counter() - t0) * 1e3, float(rejected))
