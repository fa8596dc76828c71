"""Elementwise maths that gives the same bits on every processor: the C library's functions, compiled.

numpy computes ``arccos``, ``arcsin``, ``arctan2``, ``power``, ``exp``, ``log``... with its own vector code
on processors with AVX-512 and with the C library's functions elsewhere, and the two differ in the last
bits. Small as that is, it reaches discrete choices: the palm's mesh is the convex hull of sphere samples
(a sample on the hull or not), and a start search picks among fits that score nearly alike. The same
real SR305 frames gave 18 of 19 within every floor on an AVX-512 EPYC and 15 on an AVX2 one, with
numpy's ``arccos`` of the sphere samples the only difference. Wherever a result must not depend on the
processor, these stand in for numpy's: they call the C library (as numpy does without AVX-512), from
compiled loops (numba does not vectorise them: no SVML).

>>> import numpy as np
>>> x = np.array([-1.0, 0.0, 0.5, 1.0])
>>> bool(np.allclose(acos(x), np.arccos(x), rtol=1e-15, atol=0))
True
>>> bool(np.all(atan2(np.array([1.0, -1.0]), np.array([0.0, 0.0])) == np.array([np.pi / 2, -np.pi / 2])))
True
"""
from __future__ import annotations

import math

from numba import vectorize


@vectorize(["float64(float64)"], cache=True)
def acos(x):
    """arccos (radians; NaN outside [−1, 1])."""
    return math.acos(x) if -1.0 <= x <= 1.0 else math.nan


@vectorize(["float64(float64)"], cache=True)
def asin(x):
    """arcsin (radians; NaN outside [−1, 1])."""
    return math.asin(x) if -1.0 <= x <= 1.0 else math.nan


@vectorize(["float64(float64, float64)"], cache=True)
def atan2(y, x):
    """The angle of (x, y) (radians, in [−π, π])."""
    return math.atan2(y, x)


@vectorize(["float64(float64, float64)"], cache=True)
def power(x, p):
    """x ** p (NaN for a negative x and a fractional p, as numpy)."""
    if x < 0.0 and p != math.floor(p):
        return math.nan
    return math.pow(x, p)
