"""Full-frame arrays reused from frame to frame (:class:`FrameBuffers`, one per :class:`Segmenter`)."""
from __future__ import annotations

import sys
import threading

import numpy as np


class FrameBuffers:
    """Arrays of a frame's size that a :class:`tracker.segment.Segmenter` hands out frame after frame (the
    observation's mask, depth and silhouette, the frame converted to float64): one allocation per name,
    size and type while the previous ones are free, instead of one per frame.

    A fresh full-frame array is not always free: freed between frames, its pages can go back to the
    system (glibc returns big blocks) and the next one faults them in again — ``observe`` called frame
    after frame on the realistic scenes' frames (bench_segmented's, replayed) took 5.1–5.5 ms a colour
    frame so, 2.6–2.9 with its arrays reused (docs/experiments/depth-only-scenes.md); inside the
    tracking loop the tracker's own allocations kept the heap in place and it made no difference.

    A buffer is handed out again only when nothing else refers to it: no observation, array or view of
    it (a view refers to it as its base) is alive — an observation kept by the caller keeps its arrays,
    and the next frame gets others (up to :attr:`SLOTS` of each kind are kept; more in use at once are
    allocated as before). Every buffer is written whole by its taker (:meth:`zeros`, :meth:`full`,
    :meth:`copy_of`): nothing of an earlier frame shows through. Copies and pickles of the owner start
    with no buffers."""

    #: buffers kept per name (the frame's own, the caller's previous observation, one spare)
    SLOTS = 3

    def __init__(self):
        self._pool = {}
        self._lock = threading.Lock()  # two threads observing with one segmenter never share a buffer

    def take(self, name, shape, dtype) -> np.ndarray:
        """A C-contiguous array of ``shape`` and ``dtype`` that nothing else refers to; its content is
        left from an earlier frame (write it whole)."""
        key = (tuple(int(n) for n in shape), np.dtype(dtype))
        with self._lock:
            pool = self._pool.get(name)
            if pool is None or pool[0] != key:
                # a new frame size or type drops the old buffers
                pool = self._pool[name] = (key, [])
            bufs = pool[1]
            for i in range(len(bufs)):
                # the list's reference and getrefcount's argument: nobody else holds it (or a view of it)
                if sys.getrefcount(bufs[i]) == 2:
                    return bufs[i]
            buf = np.empty(key[0], key[1])
            if len(bufs) < self.SLOTS:
                bufs.append(buf)
            return buf

    def zeros(self, name, shape, dtype=bool) -> np.ndarray:
        """:meth:`take` set to zero (``np.zeros``)."""
        out = self.take(name, shape, dtype)
        out.fill(0)
        return out

    def full(self, name, shape, value, dtype=np.float64) -> np.ndarray:
        """:meth:`take` set to ``value`` (``np.full``)."""
        out = self.take(name, shape, dtype)
        out.fill(value)
        return out

    def copy_of(self, name, a, dtype=None) -> np.ndarray:
        """A copy of ``a`` as ``dtype`` (its own type when None): ``np.array(a, dtype)``'s values."""
        a = np.asarray(a)
        out = self.take(name, a.shape, a.dtype if dtype is None else dtype)
        np.copyto(out, a, casting="unsafe")
        return out

    def __getstate__(self):
        return {}

    def __setstate__(self, state):
        self.__init__()

    def __deepcopy__(self, memo):
        return FrameBuffers()
