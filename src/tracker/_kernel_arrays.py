"""The arrays the tracker's numba kernels share, as named tuples (numba passes a ``NamedTuple`` of
arrays and scalars into compiled code and reads its fields by name there).

Every stage's kernels module (``_observe_kernels``, ``_correspond_kernels``, ``_silhouette_kernels``,
``_fit_kernels``, ``_search_kernels``, ``_wrist_kernels``) takes these instead of the same arrays
position by position. A field's type fixes the compiled version: build them with the constructors
below (``of``), which convert each field to the dtype the kernels were compiled for.

Python calls a kernel through its ``*_entry`` function with each named tuple as a plain tuple
(:func:`plain`); the entry names them again in compiled code. numba types a plain tuple's arguments in
its compiled dispatcher and a ``NamedTuple``'s in Python, on every call: a fit with no points costs 30 µs
a call given the named tuples and 20 µs through its entry (a tracked frame takes about 1 ms).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np


def plain(*args) -> tuple:
    """``args`` with every named tuple as a plain tuple (the arguments of a kernel's ``*_entry``)."""
    return tuple([tuple(a) if isinstance(a, tuple) else a for a in args])


class HandArrays(NamedTuple):
    """A :class:`handmodel.HandModel`'s kinematic tree (:meth:`HandModel.kernel_args`): node parents,
    rest transforms, each node's DoF range (``dof_ptr`` into ``dof_idx``), DoF types and axes."""

    parents: np.ndarray
    rest: np.ndarray
    dof_ptr: np.ndarray
    dof_idx: np.ndarray
    dof_types: np.ndarray
    dof_axes: np.ndarray

    @classmethod
    def of(cls, hand):
        return cls(*hand.kernel_args())


class CapsuleArrays(NamedTuple):
    """The capsule surface (:class:`handmodel.geometry.Capsules`): per primitive its node, shape
    (round cone or palm slab), length, end radii and thickness."""

    node: np.ndarray
    shape: np.ndarray
    length: np.ndarray
    r0: np.ndarray
    r1: np.ndarray
    thickness: np.ndarray

    @classmethod
    def of(cls, caps):
        return cls(*caps.kernel_args())


class SampleArrays(NamedTuple):
    """Model surface samples in their nodes' frames (:class:`tracker.correspond.ModelSamples`)."""

    nodes: np.ndarray
    local: np.ndarray
    local_n: np.ndarray

    @classmethod
    def of(cls, samples):
        return cls(samples.nodes, samples.local, samples.local_n)


class SilhouetteArrays(NamedTuple):
    """A frame's silhouette window (:class:`tracker.correspond.Silhouette`) with its camera: the
    distance transform ``dist`` and its nearest mask pixel ``iv``/``iu`` over the window at
    ``(v0, u0)``, the frame's ``depth`` (m) and the intrinsics."""

    fx: float
    fy: float
    cx: float
    cy: float
    dist: np.ndarray
    iv: np.ndarray
    iu: np.ndarray
    depth: np.ndarray
    v0: int
    u0: int

    @classmethod
    def of(cls, sil, *, depth=None):
        cam = sil.camera
        return cls(float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy), sil.dist, sil.iv, sil.iu,
                   sil.depth if depth is None else depth, int(sil.v0), int(sil.u0))


class MatchRules(NamedTuple):
    """How data→model pairs are found and kept (:class:`tracker.correspond.CorrespondSettings`):
    the camera centre, front-facing surface only, the rejection distance (m) and the normals' least
    cosine (−1 = no normal test)."""

    camera: np.ndarray
    facing_only: bool
    reject_m: float
    agreement: float


class Pairs(NamedTuple):
    """Output rows of a closest-point pass, one per data point: the model point, its normal, the
    primitive (−1 none), the distance (m), the node and whether the pair is kept."""

    p: np.ndarray
    n: np.ndarray
    seg: np.ndarray
    d: np.ndarray
    node: np.ndarray
    valid: np.ndarray

    @classmethod
    def empty(cls, P, seg=None):
        return cls(np.zeros((P, 3)), np.zeros((P, 3)), np.empty(P, np.int64) if seg is None else seg,
                   np.empty(P), np.zeros(P, np.int64), np.empty(P, np.bool_))


class StageArrays(NamedTuple):
    """The stages of one fit, one row each, padded to the widest subspace: basis ``M (S, n, m)``,
    offset ``mu (S, n)``, dimension ``m (S,)``, limits ``lo``/``hi`` and damping ``damp (S, m)``,
    ``eye (S,)`` (M is the identity), ``entry (S,)`` (:data:`ENTRY_NONE`, :data:`ENTRY_CLAMP`,
    :data:`ENTRY_THROUGH`), ``local (S,)`` (a local pass may replace the closest-point search), and
    the model's ``pose_mask (n,)`` (the global pose DoF)."""

    M: np.ndarray
    mu: np.ndarray
    m: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    damp: np.ndarray
    eye: np.ndarray
    entry: np.ndarray
    local: np.ndarray
    pose_mask: np.ndarray


class ProjectionArrays(NamedTuple):
    """The projection after each stage (``on (S,)``), its subspace as :class:`StageArrays`' rows."""

    on: np.ndarray
    M: np.ndarray
    mu: np.ndarray
    m: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    eye: np.ndarray


class GaussNewton(NamedTuple):
    """One stage's damped Gauss-Newton (:class:`handmodel.solver.SolverSettings`): steps, halvings
    of a step that does not lower the energy, the relative gain that ends a stage, joint-limit
    damping, clamping and the margin kept from a limit."""

    iterations: int
    max_halvings: int
    tol: float
    limit_avoid: bool
    clamp: bool
    margin: float

    @classmethod
    def of(cls, solver):
        return cls(int(solver.iterations), int(solver.max_halvings), float(solver.tol),
                   bool(solver.joint_limit_avoidance), bool(solver.clamp), float(solver.clamp_margin))


class FitTerms(NamedTuple):
    """What a fit's energy holds besides the data pairs (:class:`tracker.icp.IcpSettings`): the
    Cauchy scale (mm, 0 = plain least squares), point-to-plane residuals, Gauss-Newton on moment
    sums, how far (m) the model may move before a local pass searches again, the silhouette term
    (on, its weight, its tolerance in px) and the rigid steps before the stages."""

    robust_mm: float
    point_to_plane: bool
    moments: bool
    local_m: float
    silhouette: bool
    silhouette_weight: float
    silhouette_px: float
    n_rigid: int


class WristLine(NamedTuple):
    """The wrist-line pair: on, the model's wrist crease as node ``node`` and offset ``local``, the
    plane's unit ``normal`` through the camera centre, the pair's weight as a share of the valid data
    pairs and the distance (m) from the plane within which it is free."""

    on: bool
    node: int
    local: np.ndarray
    normal: np.ndarray
    share: float
    free_m: float


class KeypointPairs(NamedTuple):
    """The detected keypoints' pairs (:class:`tracker.icp_settings.KeypointTermSettings`): on, the model's
    keypoint nodes (a keypoint is its node's origin), the detected positions, each pair's weight as a
    share of the valid data pairs, and the Cauchy scale (m) of the pairs' own robust weight."""

    on: bool
    nodes: np.ndarray
    target: np.ndarray
    share: np.ndarray
    scale_m: float


class ScoreTerms(NamedTuple):
    """The terms of the start search's score (:func:`tracker.init.score`): what a rejected pair adds
    and the cap of a point's data cost (mm), the model→data term (on, its weight, tolerances in mm and
    px, cap in mm)."""

    rejected_mm: float
    data_cap_mm: float
    m2d: bool
    m2d_weight: float
    m2d_tolerance_mm: float
    m2d_tolerance_px: float
    m2d_cap_mm: float


class WristCueArrays(NamedTuple):
    """A wrist cue for the search's score (:func:`tracker.wrist.wrist_cost_mm`): on, the point where
    the arm meets the hand (camera frame), the arm's direction in the image, and the cost's reach and
    turn (mm)."""

    on: bool
    point: np.ndarray
    direction: np.ndarray
    reach_mm: float
    turn_mm: float


# stand-ins of the model→data and silhouette arrays' types when their term is off (one compiled
# version serves both)
NO_KEYPOINTS = KeypointPairs(False, np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0), 1.0)
NO_SAMPLES = SampleArrays(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
NO_SILHOUETTE = SilhouetteArrays(1.0, 1.0, 0.0, 0.0, np.zeros((1, 1)), np.zeros((1, 1), np.int32),
                                 np.zeros((1, 1), np.int32), np.zeros((1, 1)), 0, 0)

# a stage's way into its subspace (tracker.icp.Stage.entry)
ENTRY_NONE, ENTRY_CLAMP, ENTRY_THROUGH = 0, 1, 2
