"""The settings of one ICP fit (:func:`tracker.icp.fit`): :class:`IcpSettings`, the iterations and
the estimation, with its nested groups, the local passes (:class:`LocalPassSettings`) and the
wrist-line pair (:class:`WristLineSettings`); and the detected keypoints' term (:class:`KeypointTermSettings`,
``TrackerSettings.refine.keypoints``: the tracker decides where it acts, :func:`tracker.icp.fit` weighs it).

>>> s = IcpSettings().replace(local=dict(stages_per_pass=1))
>>> (s.stages_per_pass, s.local_mm, IcpSettings.paper().wrist_line_weight)
(1, 1.0, 0.0)
"""
from __future__ import annotations

from dataclasses import dataclass, field

from handmodel.solver import SolverSettings

from .errors import TrackerError
from .settings_base import SettingsGroup


@dataclass(frozen=True)
class LocalPassSettings(SettingsGroup):
    """Local passes: after a search of every primitive for each data point's closest (the rigid step's
    counted as a stage), up to ``stages_per_pass`` − 1 synergy-subspace stages re-project each point onto
    the primitive it was matched to, the silhouette pairs kept, while the model moved less than ``mm``
    (mm) since the pass before (1 = a search per stage, the paper's; 3 and 1.0)."""

    stages_per_pass: int = 3
    mm: float = 1.0

    def check(self):
        if self.stages_per_pass < 1 or not self.mm >= 0:
            raise TrackerError("settings", f"stages_per_pass must be ≥ 1 and local_mm ≥ 0, got {self.stages_per_pass}"
                               f" and {self.mm}")


@dataclass(frozen=True)
class WristLineSettings(SettingsGroup):
    """In a fit given the frame's wrist cue (a start's last fits), one more pair holds the model's wrist
    crease on the arm's centre line in the image (:func:`tracker.wrist.arm_line_normal`), weighing like
    ``weight`` of the valid data pairs (0 = off, the paper's; 0.01), while the crease lies more than
    ``mm`` across from that line (mm; 3.0), and only up to it."""

    weight: float = 0.01
    mm: float = 3.0

    def check(self):
        if not self.weight >= 0 or not self.mm >= 0:
            raise TrackerError("settings", "wrist_line_weight and wrist_line_mm must not be negative")


@dataclass(frozen=True)
class KeypointTermSettings(SettingsGroup):
    """``refine.keypoints``: in a tracked frame's fit, the keypoint detector's keypoints (issue 38's per-frame
    term; Tkach et al. 2016/2017 and Taylor et al. 2016 pair a learned detector's keypoints with the
    model fit the same way): one pair per keypoint found on a joint the last fit saw (the unseen ones are
    the synergy prior's, :class:`tracker.parts.UnseenPrior`), from the model's keypoint to the detected one,
    all 21 together weighing like ``weight`` of the valid data pairs, each in proportion to the
    detector's confidence in it and Cauchy-weighted at ``mm`` (0.02 and 20.0; off unless ``on``). With
    ``unseen_only`` (True) only on frames after one whose fit left a joint without data
    (:class:`tracker.parts.UnseenPrior`'s test): where the data constrain every joint the keypoints would
    only pull the fit off, and their detector's ~4 ms a frame are saved.
    The detector's keypoints are 10–17 mm off where the data term fits a hand to 3–5 mm, so the weight
    is small. Off by default (``on``; ``tracker track --keypoint-term``): it draws a fist seen from its
    side towards the hand (the harder scenes 11.35 → 10.3 mm) and a grasp seen from the back, which the
    synergy prior fills well, a little away (the paper's occluded grasp 1.29 → 1.59°;
    ``docs/experiments/detector.md``, "The keypoint term in the tracked fit")."""

    on: bool = False
    weight: float = 0.02
    mm: float = 20.0
    unseen_only: bool = True

    def check(self):
        if not self.weight >= 0 or not self.mm > 0:
            raise TrackerError("settings", f"refine.keypoints.weight must not be negative and refine.keypoints.mm "
                                           f"must be positive, got {self.weight} and {self.mm}")


@dataclass(frozen=True)
class IcpSettings(SettingsGroup):
    """Iterations and the estimation of one ICP fit (why each default: ``docs/tracker.md``).

    rigid_iterations, icp_iterations : rigid, then non-rigid iterations per tracked frame (the paper: 1 + 4)
    gn_iterations : Gauss-Newton steps per non-rigid iteration (5)
    damping, pose_damping : λ on posture and on the global pose (residuals in mm; the paper's 1 and 0)
    robust_mm : Cauchy scale of the data-term weights (mm; 0 = plain least squares, the paper's; 8)
    silhouette_weight : the model→data term's weight (0 = off, the paper's; 1)
    point_to_plane : point-to-plane data residuals (False)
    projected_steps : reduced mode: last iterations with all DoF, projected onto the PCs (0 = the paper's α-only)
    coarse_iterations : hierarchical mode: iterations in the synergy subspace first (1)
    local : local passes between closest-point searches (:class:`LocalPassSettings`, read as
        ``stages_per_pass``, ``local_mm``; :func:`tracker.icp.tracking_schedule`)
    wrist_line : a start's wrist-line pair (:class:`WristLineSettings`, read as ``wrist_line_weight``,
        ``wrist_line_mm``; :func:`tracker.icp.fit`'s ``wrist``)
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
    local: LocalPassSettings = field(default_factory=LocalPassSettings)
    wrist_line: WristLineSettings = field(default_factory=WristLineSettings)

    # the nested groups' fields, read where the fit reads them
    stages_per_pass = property(lambda self: self.local.stages_per_pass)
    local_mm = property(lambda self: self.local.mm)
    wrist_line_weight = property(lambda self: self.wrist_line.weight)
    wrist_line_mm = property(lambda self: self.wrist_line.mm)

    @classmethod
    def paper(cls):
        """1 rigid + 4 non-rigid iterations × 5 Gauss-Newton steps, λ 1 on posture and 0 on pose, plain
        least squares, no silhouette or wrist-line term, one search per stage."""
        return cls(rigid_iterations=1, icp_iterations=4, gn_iterations=5, damping=1.0, pose_damping=0.0,
                   robust_mm=0.0, silhouette_weight=0.0, projected_steps=0, local=LocalPassSettings(stages_per_pass=1),
                   wrist_line=WristLineSettings(weight=0.0))

    def check(self):
        if self.icp_iterations < 0 or self.rigid_iterations < 0 or self.gn_iterations < 1:
            raise TrackerError("settings", "icp_iterations and rigid_iterations must be ≥ 0, gn_iterations ≥ 1")
        self.local.check()
        self.wrist_line.check()
        if (self.projected_steps < 0 or self.robust_mm < 0 or self.silhouette_weight < 0
                or not self.wrist_line_weight >= 0 or not self.wrist_line_mm >= 0):
            raise TrackerError("settings", "projected_steps, robust_mm, silhouette_weight, wrist_line_weight and "
                                           "wrist_line_mm must not be negative")

    def solver(self) -> SolverSettings:
        return SolverSettings(iterations=self.gn_iterations, damping=self.damping, pose_damping=self.pose_damping,
                              min_points=3)
