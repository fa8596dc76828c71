"""Tuning constants of the hand segmentation (metres, pixels, palm radii; see each line)."""
from __future__ import annotations




# HSV skin range of htrack's Detector (OpenCV scale: H 0–179, S and V 0–255)
SKIN_HSV = ((0, 56, 113), (179, 174, 255))
FOREARM_CHOICES = ("cut", "keep")
PLANE_CHOICES = ("auto", "cut", "keep")
FIND = object()  # Segmenter's ``plane`` argument when the frame's plane is to be found there
PLANE_SAMPLES = 5000  # pixels of the frame the plane search samples (every 8th pixel each way of 640 x 480)
PLANE_TRIES = 256  # planes through three sampled points tried (a table on a third of the samples: no triplet of it in 1 of 16,000 frames)
PLANE_PREEMPT, PLANE_KEEP = 8, 6  # each tried plane weighed on every 8th sample, the best 6 on all
PLANE_TOL_M = 0.012  # a sample this close to a tried plane is on it (Kinect v1 noise and steps at 1.5 m: ~7 mm)
PLANE_MIN_AREA_M2 = 0.1  # a plane is a support surface when it covers this much (a 1.5x hand: 0.027 m²) …
# … and is seen this far off face-on (the rendered table: 42°). A surface facing the camera behind the
# hand is left to the layer rule (_in_front): leaving out a flat torso 4 cm behind lost the SR305 hands
PLANE_MIN_TILT_DEG = 30.0
PLANE_BAND_M = (0.008, 0.02)  # the band left out around it: 3 robust SDs of its points, within these
DEFAULT_FOCAL_PX = 500.0  # pixel size for physical areas when the camera is not given
EDGE_GAP_PX = 2  # a small piece this close to another hand-sized surface at its depth is a piece of it (_edge_pieces)
PALM_WIDTH_SHARE = 0.93  # places at least this share of the widest count as palm candidates …
PALM_FILL_SLACK = 0.1  # … when the mask fills their disk within this share of the best-filled one …
PALM_FILL_MIN = 0.85  # … or at least this share of it (_filled_places)
NO_NARROWING_WRIST = 1.3  # least wrist distance (palm radii) from the palm centre when nothing narrows sharply
TAPER_WINDOW_R = 0.4  # … and how far (palm radii) a slow taper must stop falling for its end to be the wrist …
TAPER_MIN_SAMPLES = 4  # … and over at least this many samples (_end_of_taper's window)
ARM_REACH_R = 4.5  # a part leaving the palm farther than this many palm radii from its centre is no finger
SURE_ARM_REACH_R = 8.0  # a part leaving the palm farther than this is an arm even when it crosses the finger ring in pieces
OPPOSITE_ARM_REACH_R = 2.6  # a wide part opposite the fingers is an arm when it reaches at least this far
ARM_BEND_DEG = 10.0  # the arm's own direction sets the cut when it is this far off the palm centre's (see cut_forearm)
ARM_LENGTH_PALMS = 3.5  # an object longer than this many palm widths is a hand with its arm
FINGER_MAX_M = 0.035  # parts narrower than this are finger-like (fingers of 0.8-1.5x hands: 14-27 mm; a forearm 30-70 mm)
FINGER_MIN_AREA_M2 = 1.5e-4  # a finger-like part is at least this big (a finger's last 1-2 cm; outline noise is smaller) …
TOUCH_PX = 3  # another surface this close in the image (sensor shadows between them are 1-3 px) …
TOUCH_M = 0.02  # … and in depth joins the hand's region there …
TOUCH_AREA_M2 = 0.0015  # … when it is this big near the hand (a table, the body; shading specks are smaller)
TOUCH_WINDOW_M = 0.06  # how far around the hand that size is measured
FINGER_ELONGATION = 2.5  # … at least this many times longer than wide (rendered and real fingers: 3.4-7) …
FINGER_MIN_LENGTH_M = 0.025  # … and this long (4 standard deviations along it)
FINGER_RIM_M = 0.003  # … counted from this far off the rest of the shape (_finger_pieces)
FINE_FINGER_M = 0.015  # a full-resolution pixel belongs to its coarse pixel's surface within this depth (_has_fingers)
FINE_FINGER_GROW = 1  # … and, when none are found there, this many coarse pixels beyond the surface too (fragments)
FRONT_WINDOW_M = 0.08  # a pixel's local background is the farthest depth this close (> half a 1.5x hand's palm width)
FRONT_STEP_M = 0.01  # the hand's layer is nearer than its local background by more than this
FRONT_OUTLINE_SHARE = 0.3  # … the region lies behind it across that step over this share of its outline (hand and arm alone, or the table scenes: ≤ 0.22 with colour; a torso 3-5 cm behind: 0.27-0.95)
FRONT_BEHIND_AREA_M2 = 0.035  # … and the region behind it is bigger than any hand (1.5x: 0.027 m²; a torso within reach: 0.04-0.1)
# depth only, when the nearest whole surface has no fingers: the surfaces tried instead, at most this many,
# whose nearest part lies within this depth of its own (the rendered boxes: 5 mm; a torso 18 cm behind a
# fist, split by the arm's shadow into finger-like strips, was taken) and no bigger than a hand with its
# forearm (rendered 1x: 0.02 m²; that torso's visible part 0.09)
FINGERS_FIRST_TRIES, FINGERS_FIRST_M, FINGERS_FIRST_MAX_AREA_M2 = 4, 0.1, 0.06
BORDER_PX = 12  # a seed this close to the image border counts as cut off by it (sensors leave the last pixels empty)
