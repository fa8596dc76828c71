"""Pipeline stage ``segment``: the hand's pixels in a depth (and colour) frame — working volume,
nearest hand-sized surface, fingertip blobs, wrist cut, skin colour.

No wristband is needed. The steps, each a small function over arrays:

1. working volume: valid depth within ``[z_min, z_max]`` (and inside ``box`` when given);
2. :func:`surfaces`: pixels grouped into surfaces by depth continuity (neighbours closer than
   ``jump``), so the body and objects behind or beside the hand, and a table the hand rests on
   but stands out of, fall into other surfaces;
3. :func:`hand_region`: among surfaces of at least ``min_area`` square metres (flying pixels
   and specks do not count), the one whose nearest part is nearest to the camera;
4. that surface, cut to ``band`` metres behind its nearest part, plus the small surfaces in that
   depth band within ``margin_px`` of it (fingertips curled towards the camera that the sensor
   cuts off by a depth jump or a no-data gap). The hand is the end of an arm with fingers: an
   arm reaching towards the camera from outside the image, nearer than that surface, is taken
   instead when its far end has fingers and lies in front of it (a body a few centimetres
   behind the hand); and when the surface is a whole arm in view (it does not reach the border
   and is much longer than a palm is wide), the search starts from its end with the fingers
   (:func:`_hand_end`), since a free-ended arm's nearest part can be its far end. A body a few
   centimetres behind the hand, which the arm joins to the hand's surface, is left out: the region
   is then the layer in front of its local background (:func:`_in_front`);
5. :func:`cut_forearm` (``forearm="cut"``): the palm is the largest inscribed circle of the
   region, the forearm the wide part leaving it that goes on (past the border, the band or the
   reach, or into another object met at its own depth: a table, the body); the cut goes across
   the arm where the width profile along the arm stops narrowing (the wrist);
6. with a colour frame (``use_color``), only skin-coloured pixels (HSV range of htrack's
   detector) are kept, when enough of them are;
7. without one (``plane="auto"``), the pixels of the frame's largest plane (a table, a floor, a
   wall: :func:`support_plane`) are left out as the skin test leaves them out: an arm resting on a
   table is then no longer one surface with it.

The body-sized surface of a person standing behind the hand is never picked over the hand
because its nearest part lies behind the hand; a surface that merely touches the hand in the
image is a different surface as soon as a depth step separates them.

>>> d = np.full((60, 80), 0.9)          # a wall
>>> d[10:40, 20:40] = 0.5               # a hand-sized patch (≈ 6 × 4 cm at f = 500 px) in front
>>> m = Segmenter(min_area=1e-4)(d, focal=500.0)
>>> int(m.sum()), bool(m[20, 30]), bool(m[5, 5])
(600, True, False)
"""
from __future__ import annotations

import numpy as np  # noqa: F401  (the doctest above)

from .constants import FIND, FOREARM_CHOICES, PLANE_CHOICES, TUNING, SegmentConstants
from .forearm import cut_forearm
from .ops import bounds, in_box, largest_component
from .plane import SupportPlane, support_plane
from .region import Region, hand_region
from .segmenter import Segmenter
from .skin import rgb_to_hsv, skin_mask
from .surfaces import focal_from_points, pixel_area, refine, surface_fronts, surfaces

__all__ = ["FIND", "FOREARM_CHOICES", "PLANE_CHOICES", "TUNING", "Region", "SegmentConstants", "Segmenter",
           "SupportPlane", "bounds", "cut_forearm", "focal_from_points", "hand_region", "in_box", "largest_component",
           "pixel_area", "refine", "rgb_to_hsv", "skin_mask", "support_plane", "surface_fronts", "surfaces"]
