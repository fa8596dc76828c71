"""numba kernel of the RVL depth codec (Wilson's run-length / variable-length code, as ROS's
``compressed_depth_image_transport`` writes it); :func:`tracker.io.images.decode_rvl` checks and wraps it."""
import numba
import numpy as np

#: Kernel status: decoded, or why not (the stream ended early, a run overflows the image, a value
#: needs more than 32 bits). Damaged input never reads or writes out of bounds.
RVL_OK, RVL_SHORT, RVL_OVERRUN, RVL_VALUE = 0, 1, 2, 3


@numba.njit(cache=True)
def rvl_decode(words, n):  # pragma: no cover - compiled
    """Depth units ``(n,)`` uint16 and a status (:data:`RVL_OK` or the first problem) from RVL words."""
    out = np.zeros(n, np.uint16)
    wi = 0
    left = 0          # nibbles left in `word`
    word = np.uint32(0)
    pos = 0
    prev = 0
    phase = 0         # 0: a run of zeros, 1: a run of non-zeros, 2+: deltas of that run
    run = 0
    while pos < n:
        # one variable-length value: 3 bits a nibble, most significant nibble of each word first
        value = 0
        shift = 0
        while True:
            if left == 0:
                if wi >= words.size:
                    return out, RVL_SHORT
                word = words[wi]
                wi += 1
                left = 8
            nib = (word >> np.uint32(28)) & np.uint32(15)
            word = (word << np.uint32(4)) & np.uint32(0xFFFFFFFF)
            left -= 1
            if shift > 30:
                return out, RVL_VALUE
            value |= int(nib & np.uint32(7)) << shift
            shift += 3
            if (nib & np.uint32(8)) == 0:
                break
        if phase == 0:
            if value > n - pos:
                return out, RVL_OVERRUN
            pos += value          # zeros: out is zero already
            phase = 1
        elif phase == 1:
            if value > n - pos:
                return out, RVL_OVERRUN
            run = value
            phase = 0 if run == 0 else 2
        else:
            delta = (value >> 1) ^ -(value & 1)
            prev = (prev + delta) & 0xFFFF
            out[pos] = prev
            pos += 1
            run -= 1
            if run == 0:
                phase = 0
    return out, RVL_OK
