"""Tuning constants of the hand segmentation, in one frozen dataclass (:class:`SegmentConstants`) with one
instance, :data:`TUNING`, that every module of :mod:`tracker.segment` reads (as ``K.TUNING.name``).

The values are measured, not chosen: each field's comment says its unit and what set it. A test that
turns a rule off replaces the instance, ``monkeypatch.setattr(K, "TUNING", K.TUNING.replace(name=value))``.
The settings a user chooses (depth range, band, reach, …) are :class:`tracker.segment.Segmenter`'s."""
from __future__ import annotations

from dataclasses import dataclass, replace

FOREARM_CHOICES = ("cut", "keep")
PLANE_CHOICES = ("auto", "cut", "keep")
FIND = object()  # Segmenter's ``plane`` argument when the frame's plane is to be found there


@dataclass(frozen=True)
class SegmentConstants:
    """The segmentation's tuning constants (units in each name or comment: m, m², px, deg, palm radii r)."""

    # skin colour: HSV range of htrack's Detector (OpenCV scale: H 0–179, S and V 0–255)
    skin_hsv: tuple = ((0, 56, 113), (179, 174, 255))
    # the support plane (support_plane)
    # pixels of the frame the plane search samples (every 8th pixel each way of 640 x 480)
    plane_samples: int = 5000
    # planes through three sampled points tried (a table on a third of the samples: no triplet of it in 1 of
    # 16,000 frames)
    plane_tries: int = 256
    plane_preempt: int = 8  # each tried plane weighed on every 8th sample …
    plane_keep: int = 6  # … the best 6 on all
    # a sample this close to a tried plane is on it (Kinect v1 noise and steps at 1.5 m: ~7 mm)
    plane_tol_m: float = 0.012
    # a plane is a support surface when it covers this much (a 1.5x hand: 0.027 m²) …
    plane_min_area_m2: float = 0.1
    # … and is seen this far off face-on (the rendered table: 42°). A surface facing the camera behind the
    # hand is left to the layer rule (_in_front): leaving out a flat torso 4 cm behind lost the SR305 hands
    plane_min_tilt_deg: float = 30.0
    plane_band_m: tuple = (0.008, 0.02)  # the band left out around it: 3 robust SDs of its points, within these
    default_focal_px: float = 500.0  # pixel size for physical areas when the camera is not given
    # a seed this close to the image border counts as cut off by it (sensors leave the last pixels empty)
    border_px: int = 12
    # a small piece this close to another hand-sized surface at its depth is a piece of it (_edge_pieces)
    edge_gap_px: int = 2
    # the palm (cut_forearm, _filled_places)
    palm_width_share: float = 0.93  # places at least this share of the widest count as palm candidates …
    palm_fill_slack: float = 0.1  # … when the mask fills their disk within this share of the best-filled one …
    palm_fill_min: float = 0.85  # … or at least this share of it (_filled_places)
    # the widest place within fingers' reach of the region's far end is the palm when at least this share of the
    # widest place's width (_hand_end_palm; realistic fist-side scenes: fists seen from the thumb side 0.83-1.08 of
    # the forearm's width, the fingers of the opening hand seen edge-on 0.28-0.44)
    hand_end_width_share: float = 0.6
    # … and its radius need only be this (m; cut_forearm's palm_radius_m otherwise): a fist seen from the thumb side
    # is thinner than a palm is wide (0.8x, Kinect v1 and SR305 noise: 14 mm)
    side_fist_radius_m: float = 0.013
    # such a fist's wrist ends the narrowest stretch (its heel: widths within this share of the least) …
    heel_width_tol: float = 0.1
    # … within this many of its radii r of the region's far end (the fist-side scenes: the rendered wrist 4.6-5.3 r)
    heel_reach_r: float = 6.0
    # the wrist and the arm (cut_forearm), in palm radii r unless the name says otherwise
    no_narrowing_wrist: float = 1.3  # least wrist distance (r) from the palm centre when nothing narrows sharply
    taper_window_r: float = 0.4  # … and how far (r) a slow taper must stop falling for its end to be the wrist …
    taper_min_samples: int = 4  # … and over at least this many samples (_end_of_taper's window)
    arm_reach_r: float = 4.5  # a part leaving the palm farther than this many r from its centre is no finger
    # a part leaving the palm farther than this is an arm even when it crosses the finger ring in pieces
    sure_arm_reach_r: float = 8.0
    # a wide part opposite the fingers is an arm when it reaches at least this far
    opposite_arm_reach_r: float = 2.6
    # the arm's own direction sets the cut when it is this far off the palm centre's (see cut_forearm)
    arm_bend_deg: float = 10.0
    arm_length_palms: float = 3.5  # an object longer than this many palm widths is a hand with its arm
    # fingers (_has_fingers, _finger_pieces)
    # parts narrower than this are finger-like (fingers of 0.8-1.5x hands: 14-27 mm; a forearm 30-70 mm)
    finger_max_m: float = 0.035
    # a finger-like part is at least this big (a finger's last 1-2 cm; outline noise is smaller) …
    finger_min_area_m2: float = 1.5e-4
    # … at least this many times longer than wide (rendered and real fingers: 3.4-7) …
    finger_elongation: float = 2.5
    finger_min_length_m: float = 0.025  # … and this long (4 standard deviations along it)
    finger_rim_m: float = 0.003  # … counted from this far off the rest of the shape (_finger_pieces)
    # a full-resolution pixel belongs to its coarse pixel's surface within this depth (_has_fingers)
    fine_finger_m: float = 0.015
    # … and, when none are found there, this many coarse pixels beyond the surface too (fragments)
    fine_finger_grow: int = 1
    # another object touching the hand (_joins)
    touch_px: int = 3  # another surface this close in the image (sensor shadows between them are 1-3 px) …
    touch_m: float = 0.02  # … and in depth joins the hand's region there …
    # … when it is this big near the hand (a table, the body; shading specks are smaller)
    touch_area_m2: float = 0.0015
    touch_window_m: float = 0.06  # how far around the hand that size is measured
    # a body close behind the hand (_in_front)
    # a pixel's local background is the farthest depth this close (> half a 1.5x hand's palm width)
    front_window_m: float = 0.08
    front_step_m: float = 0.01  # the hand's layer is nearer than its local background by more than this
    # … the region lies behind it across that step over this share of its outline (hand and arm alone, or the
    # table scenes: ≤ 0.22 with colour; a torso 3-5 cm behind: 0.27-0.95)
    front_outline_share: float = 0.3
    # … and the region behind it is bigger than any hand (1.5x: 0.027 m²; a torso within reach: 0.04-0.1)
    front_behind_area_m2: float = 0.035
    # depth only, when the nearest whole surface has no fingers: the surfaces tried instead, at most this many,
    # whose nearest part lies within this depth of its own (the rendered boxes: 5 mm; a torso 18 cm behind a
    # fist, split by the arm's shadow into finger-like strips, was taken) and no bigger than a hand with its
    # forearm (rendered 1x: 0.02 m²; that torso's visible part 0.09)
    fingers_first_tries: int = 4
    fingers_first_m: float = 0.1
    fingers_first_max_area_m2: float = 0.06

    def replace(self, **changes) -> "SegmentConstants":
        """A copy with ``changes`` (field names), e.g. a test turning one rule off."""
        return replace(self, **changes)


#: The constants every segmentation module reads (one owner).
TUNING = SegmentConstants()
