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

import numpy as np
from numba import njit

# Compiled loops behind plain functions, not numba ufuncs (@vectorize): a ufunc's wrapper is built anew
# in every process (~0.1 s each, 0.45 s at every import of the hand model); a cached njit loop loads
# at its first call.


@njit(cache=True)
def _acos(x, out):
    for i in range(x.size):
        out[i] = math.acos(x[i]) if -1.0 <= x[i] <= 1.0 else math.nan


@njit(cache=True)
def _asin(x, out):
    for i in range(x.size):
        out[i] = math.asin(x[i]) if -1.0 <= x[i] <= 1.0 else math.nan


@njit(cache=True)
def _atan2(y, x, out):
    for i in range(x.size):
        out[i] = math.atan2(y[i], x[i])


@njit(cache=True)
def _power(x, p, out):
    for i in range(x.size):
        if x[i] < 0.0 and p[i] != math.floor(p[i]):
            out[i] = math.nan
        else:
            out[i] = math.pow(x[i], p[i])


def _apply(kernel, *args):
    """``kernel`` over the broadcast float64 arrays ``args``: an array of their shape, a scalar for scalars."""
    arrays = np.broadcast_arrays(*(np.asarray(a, np.float64) for a in args))
    flat = [np.ascontiguousarray(a).reshape(-1) for a in arrays]
    out = np.empty(arrays[0].shape)
    kernel(*flat, out.reshape(-1))
    return out[()] if out.ndim == 0 else out


def acos(x):
    """arccos (radians; NaN outside [−1, 1])."""
    return _apply(_acos, x)


def asin(x):
    """arcsin (radians; NaN outside [−1, 1])."""
    return _apply(_asin, x)


def atan2(y, x):
    """The angle of (x, y) (radians, in [−π, π])."""
    return _apply(_atan2, y, x)


def power(x, p):
    """x ** p (NaN for a negative x and a fractional p, as numpy)."""
    return _apply(_power, x, p)
