"""PNG frames decoded by Pillow directly (``tracker.io.images._decode_png``): the array imageio's Pillow
plugin returns, to the bit, or imageio's own result and error where the file is anything else."""
import io
import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import pytest
from PIL import Image

from tracker.errors import RecordingError
from tracker.io.images import _decode_png, png_bytes


def _imageio(data):
    return np.asarray(iio.imread(data, extension=".png", plugin="pillow"))


def _same(a, b):
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)


@pytest.mark.parametrize("shape, dtype", [((48, 64), np.uint16), ((48, 64), np.uint8), ((48, 64, 3), np.uint8),
                                          ((48, 64, 4), np.uint8)])
def test_a_plain_png_decodes_to_imageios_array(shape, dtype):
    # depth (16-bit greyscale), 8-bit greyscale, colour RGB and RGBA: values over the whole range
    rng = np.random.default_rng(7)
    a = rng.integers(0, np.iinfo(dtype).max, size=shape, endpoint=True).astype(dtype)
    data = png_bytes(a)
    out = _decode_png(data, "frame.png")
    assert _same(out, _imageio(data)) and _same(out, a)
    out[0, 0] = 0  # writeable, as imageio's: callers may change the frame in place


def _pillow_png(save):
    buf = io.BytesIO()
    save(buf)
    return buf.getvalue()


def test_a_palette_or_animated_png_is_imageios_result():
    # the palette applied, every frame of an animated PNG: imageio's reading, not Pillow's first image
    pal = Image.fromarray(np.arange(48 * 64, dtype=np.uint8).reshape(48, 64) % 7).convert("P")
    frames = [Image.fromarray(np.full((48, 64), v, np.uint16)) for v in (100, 2000)]
    for data in (_pillow_png(lambda b: pal.save(b, format="PNG")),
                 _pillow_png(lambda b: frames[0].save(b, format="PNG", save_all=True, append_images=frames[1:]))):
        assert _same(_decode_png(data, "frame.png"), _imageio(data))
    assert _decode_png(data, "frame.png").shape == (2, 48, 64)


def test_a_damaged_png_is_imageios_error():
    data = png_bytes(np.arange(48 * 64, dtype=np.uint16).reshape(48, 64))
    for bad in (data[: len(data) // 2], data[:33] + b"\0" * 8 + data[41:]):
        try:
            _imageio(bad)
        except Exception as exc:
            expected = f"frame.png: unreadable PNG ({type(exc).__name__}: {exc})"
        else:
            pytest.fail("imageio read a damaged PNG")
        with pytest.raises(RecordingError) as got:
            _decode_png(bad, "frame.png")
        assert str(got.value) == expected


def test_reading_a_frame_loads_no_imageio(tmp_path):
    # imageio's import and plugin search were ~0.03 s of a one-still tracker track; writing still uses it
    p = tmp_path / "d.png"
    p.write_bytes(png_bytes(np.full((480, 640), 4000, np.uint16)))
    code = ("import sys\n"
            "from tracker.io.cameras import preset\n"
            "from tracker.io.images import read_depth_units\n"
            f"u = read_depth_units({str(p)!r}, preset('sr305'))\n"
            "print(int(u[0, 0]), 'imageio' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split() == ["4000", "False"]
