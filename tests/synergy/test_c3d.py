"""Tests of synergy.c3d against the real C3D corpus in ../shared/data (see its SOURCES.md)."""
from __future__ import annotations

import os
import struct
import tempfile
import time
import warnings
from pathlib import Path

from conftest import SHARED_DATA

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from synergy.c3d import MarkerData, read_c3d
from synergy.c3d_write import write_c3d
from synergy.errors import C3DError

DATA = SHARED_DATA
NO_DATA = f"real C3D corpus not found at {DATA} (the shared test data folder)"
C3D_DIRS = ("btk_samples", "c3dorg_samples", "c3dorg_art_hands", "ezc3d_testfiles", "dfki_hand_embodiment")

DFKI = "dfki_hand_embodiment/DERIVED_recording_tsv_to.c3d"
ART = "c3dorg_art_hands/ART-Human_hands_real_no6dof.c3d"

# What the raw reference readers do with each file (True = returns labelled points and
# frames). Checked live below, except where raw ezc3d spends 13-17 s before failing
# (a description longer than 127 bytes): there the table stands in for the run.
REFERENCE = {
    "btk_samples/others__Empty.c3d": (False, False),
    "btk_samples/others__MyCube.c3d": (True, True),
    "btk_samples/others__badParameterOffset.c3d": (False, False),
    "btk_samples/others__parameterOverflow.c3d": (True, True),
    "btk_samples/sample01__Eb015pi.c3d": (True, True),
    "btk_samples/sample01__Eb015pr.c3d": (True, True),
    "btk_samples/sample01__Eb015si.c3d": (False, True),
    "btk_samples/sample01__Eb015sr.c3d": (False, True),
    "btk_samples/sample01__Eb015vi.c3d": (True, True),
    "btk_samples/sample01__Eb015vr.c3d": (True, True),
    "btk_samples/sample02__DEC_INT.C3D": (True, True),
    "btk_samples/sample02__Dec_real.c3d": (True, True),
    "btk_samples/sample02__pc_int.c3d": (True, True),
    "btk_samples/sample02__pc_real.c3d": (True, True),
    "btk_samples/sample02__sgi_int.c3d": (False, True),
    "btk_samples/sample02__sgi_real.c3d": (False, True),
    "c3dorg_art_hands/ART-Human_hands_real_no6dof.c3d": (True, False),
    "c3dorg_art_hands/ART-Human_tools_integer_6dofLimbs.c3d": (True, False),
    "c3dorg_samples/Codamotion__codamotion_gaitwands_19970212.c3d": (True, True),
    "c3dorg_samples/Motion_Analysis_Corporation__Walk1.c3d": (True, True),
    "c3dorg_samples/NexGen_Ergonomics__test1.c3d": (True, True),
    "c3dorg_samples/sample_06__MACsample.c3d": (False, False),
    "c3dorg_samples/sample_10__TYPE-2.C3D": (True, True),
    "c3dorg_samples/sample_11__evart.c3d": (True, False),
    "c3dorg_samples/sample_13__Dance.c3d": (False, True),
    "c3dorg_samples/sample_16__basketball.c3d": (True, True),
    "c3dorg_samples/sample_18__bad_parameter_section.c3d": (False, False),
    "c3dorg_samples/sample_20__phasespace_sample.c3d": (False, False),  # no POINT parameters at all
    "c3dorg_samples/sample_22__BKINtechnologies.c3d": (False, True),
    "c3dorg_samples/sample_27__kyowadengyo.c3d": (True, False),  # ezc3d "reads" it misaligned
    DFKI: (True, True),
    "ezc3d_testfiles/FP_Type3.c3d": (True, True),
    "ezc3d_testfiles/Optotrak.c3d": (True, True),
    "ezc3d_testfiles/Qualisys.c3d": (True, True),
    "ezc3d_testfiles/Vicon.c3d": (True, True),
    "ezc3d_testfiles/read_NOTworking2.c3d": (True, True),
}
EZC3D_TOO_SLOW = {"c3dorg_samples/sample_18__bad_parameter_section.c3d",
                  "c3dorg_samples/sample_22__BKINtechnologies.c3d"}


def data_file(rel: str) -> Path:
    path = DATA / rel
    if not path.exists():
        pytest.skip(f"{NO_DATA}: missing {rel}")
    return path


def corpus() -> list:
    if not DATA.is_dir():
        return [pytest.param(None, marks=pytest.mark.skip(reason=NO_DATA), id="no-data")]
    found = sorted(str(p.relative_to(DATA)) for d in C3D_DIRS for p in (DATA / d).glob("*")
                   if p.suffix.lower() == ".c3d")
    return [pytest.param(rel, id=rel.split("/")[-1]) for rel in found]


def ezc3d_reads(path: Path) -> bool:
    import ezc3d

    try:
        pts = ezc3d.c3d(str(path))["data"]["points"]
    except Exception:
        return False
    return pts.shape[1] > 0 and pts.shape[2] > 0


def c3d_reads(path: Path) -> bool:
    import c3d

    try:
        with open(path, "rb") as fh, warnings.catch_warnings():
            warnings.simplefilter("ignore")
            reader = c3d.Reader(fh)
            labels = reader.point_labels
            n = sum(1 for _ in reader.read_frames())
    except Exception:
        return False
    return len(labels) > 0 and n > 0


def ezc3d_points_mm(path: Path) -> np.ndarray:
    """Raw ezc3d coordinates as (F, M, 3), NaN where ezc3d flags them."""
    import ezc3d

    return ezc3d.c3d(str(path))["data"]["points"][:3].transpose(2, 1, 0)


# --------------------------------------------------------------------------------------
# The whole corpus
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("rel", corpus())
def test_corpus_file_read_iff_a_reference_reader_reads_it(rel):
    path = DATA / rel
    assert rel in REFERENCE, f"new corpus file {rel}: add its reference verdict"
    ez_ok, c3d_ok = REFERENCE[rel]
    if rel not in EZC3D_TOO_SLOW:
        assert ezc3d_reads(path) == ez_ok, "raw ezc3d verdict changed"
    assert c3d_reads(path) == c3d_ok, "raw c3d verdict changed"

    if ez_ok or c3d_ok:
        d = read_c3d(path)
        assert isinstance(d, MarkerData) and d.backend in ("ezc3d", "c3d")
        assert d.n_frames >= 1 and d.n_markers >= 1
        assert d.points.shape == (d.n_frames, d.n_markers, 3) and d.points.dtype == np.float64
        assert d.residuals.shape == (d.n_frames, d.n_markers)
        assert np.array_equal(np.isnan(d.residuals), np.isnan(d.points[..., 0]))
        assert d.rate > 0 and d.units in ("mm", "cm", "m")
        assert len(d.labels) == len(d.original_labels) == d.n_markers
        valid = d.points[~np.isnan(d.points)]
        assert valid.size == 0 or np.abs(valid).max() < 20.0, "not in metres"
        if ez_ok and c3d_ok:  # both backends must tell the same story
            a, b = read_c3d(path, backend="ezc3d"), read_c3d(path, backend="c3d")
            assert np.array_equal(np.isnan(a.points), np.isnan(b.points))
            if not np.isnan(a.points).all():
                assert np.nanmax(np.abs(a.points - b.points)) < 2e-7  # 2e-4 mm: float32 of int data
            assert (a.labels, a.rate, a.first_frame, a.units, a.events) == \
                   (b.labels, b.rate, b.first_frame, b.units, b.events)
    else:
        t0 = time.perf_counter()
        with pytest.raises(C3DError) as err:
            read_c3d(path)
        assert path.name in str(err.value) and err.value.where == str(path)
        assert time.perf_counter() - t0 < 3.0, "a broken file must fail fast"


# --------------------------------------------------------------------------------------
# Byte order and storage variants of the same trial
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("floats, ints, scale_mm", [
    (["sample01__Eb015pr.c3d", "sample01__Eb015vr.c3d", "sample01__Eb015sr.c3d"],
     ["sample01__Eb015pi.c3d", "sample01__Eb015vi.c3d", "sample01__Eb015si.c3d"], 0.0833333358),
    (["sample02__pc_real.c3d", "sample02__Dec_real.c3d", "sample02__sgi_real.c3d"],
     ["sample02__pc_int.c3d", "sample02__DEC_INT.C3D", "sample02__sgi_int.c3d"], 0.2811818719),
], ids=["sample01", "sample02"])
def test_byte_order_variants_agree(floats, ints, scale_mm):
    ref, *others = [read_c3d(data_file(f"btk_samples/{n}")) for n in floats]
    int_variants = [read_c3d(data_file(f"btk_samples/{n}")) for n in ints]
    assert {d.backend for d in [ref, *others]} == {"ezc3d", "c3d"}  # MIPS needs the fallback
    for d in others + int_variants:
        assert d.labels == ref.labels and d.rate == ref.rate
        assert np.array_equal(np.isnan(d.points), np.isnan(ref.points))
    for d in others:  # Intel, DEC and MIPS floats: the same numbers
        assert np.nanmax(np.abs(d.points - ref.points)) * 1000 <= 1e-4
    for d in int_variants:  # integers: within one step of POINT:SCALE
        assert np.nanmax(np.abs(d.points - ref.points)) * 1000 <= scale_mm * 1.0001


# --------------------------------------------------------------------------------------
# Broken, truncated, empty
# --------------------------------------------------------------------------------------
# Fragments of the readers' own exception texts (py-c3d, ezc3d's C++, Python's): never in a message.
LEAKS = ("ezc3d:", "c3d:", "!", "Error", "iostream", "ignoreBadFormatting", "unpack requires", "read length",
         "index-sized", "0-dimensional", "local variable", "already exists with key", "buffer is smaller",
         "is not an INT", "Could not")


def assert_our_words(err: C3DError, path: Path, problem: str) -> None:
    """One line naming the file, then the problem as we word it, no reader's text in it."""
    text = str(err)
    assert text.startswith(f"{path}: {problem}"), text
    assert "\n" not in text and not any(leak in err.reason for leak in LEAKS), text


@pytest.mark.parametrize("rel, reason", [
    ("btk_samples/others__Empty.c3d", "empty file (0 bytes)"),
    ("btk_samples/others__badParameterOffset.c3d",
     "corrupt parameter section: parameter LABELS is 429 bytes long but its offset to the next entry is 416"),
    ("c3dorg_samples/sample_18__bad_parameter_section.c3d",
     "parameter LABELS has a description of 211 bytes (over 127)"),
    ("c3dorg_samples/sample_06__MACsample.c3d",
     "the header's scale factor 0.0551136 differs from POINT:SCALE 0.0215412"),
    ("c3dorg_samples/sample_20__phasespace_sample.c3d",
     "unreadable: no point channels (the header claims 40); no POINT group in the parameter section"),
])
def test_broken_files_raise_c3derror_naming_the_file(rel, reason):
    path = data_file(rel)
    with pytest.raises(C3DError) as err:
        read_c3d(path)
    assert_our_words(err.value, path, reason)


@pytest.mark.parametrize("rel, cut", [
    (DFKI, 0.5), (DFKI, 0.99), (DFKI, 1000), (DFKI, 1536),
    (ART, 950),            # inside the parameter section: raw ezc3d never returns on this one
    (ART, 0.3), ("btk_samples/sample01__Eb015sr.c3d", 0.6),   # MIPS: c3d backend
    ("c3dorg_samples/sample_22__BKINtechnologies.c3d", 0.7),
])
def test_truncated_copy_raises(tmp_path, rel, cut):
    raw = data_file(rel).read_bytes()
    n = int(len(raw) * cut) if cut < 1 else int(cut)
    path = tmp_path / f"cut_{Path(rel).name}"
    path.write_bytes(raw[:n])
    t0 = time.perf_counter()
    with pytest.raises(C3DError) as err:
        read_c3d(path)
    assert path.name in str(err.value)
    assert "truncated" in err.value.reason or "no frames" in err.value.reason
    assert time.perf_counter() - t0 < 3.0


def test_empty_missing_and_foreign_files(tmp_path):
    empty = tmp_path / "empty.c3d"
    empty.write_bytes(b"")
    with pytest.raises(C3DError, match="empty"):
        read_c3d(empty)
    with pytest.raises(C3DError, match="no such file"):
        read_c3d(tmp_path / "nope.c3d")
    with pytest.raises(C3DError, match="not a regular file"):
        read_c3d(tmp_path)
    text = tmp_path / "text.c3d"
    text.write_bytes(b"x" * 2048)
    with pytest.raises(C3DError, match=r"not a C3D file \(it is text\)"):
        read_c3d(text)


C3D_HEADER_START = b"\x02\x50"   # parameters from block 2, the key byte 0x50


@pytest.mark.parametrize("data, problem", [
    (b"this is not a c3d file at all\n", "not a C3D file (it is text)"),
    ("caf\u00e9 ".encode() * 200, "not a C3D file (it is text)"),       # text past the 512-byte header too
    (b"\x00" * 100, "not a C3D file (header key byte is 0x00, expected 0x50)"),
    (b"\x00" * 4096, "not a C3D file (header key byte is 0x00, expected 0x50)"),
    (b"\x00\x50" + bytes(98), "not a C3D file (its first byte, the parameter section's block number, is 0"),
    (b"\x89PNG\r\n\x1a\n" + bytes(100), "not a C3D file (it is a PNG image)"),
    (b"\x89PNG\r\n\x1a\n" + bytes(5000), "not a C3D file (it is a PNG image)"),  # 0x50 is its 2nd byte
    (b"PK\x03\x04" + bytes(600), "not a C3D file (it is a zip archive)"),
    (C3D_HEADER_START[:1], "truncated: 1 byte, shorter than the 512-byte header"),
    (C3D_HEADER_START + bytes(298), "truncated: 300 bytes, shorter than the 512-byte header"),
])
def test_short_or_foreign_file_is_truncated_only_if_it_starts_as_a_c3d(tmp_path, data, problem):
    """A file shorter than the header is truncated only when its first bytes are a C3D header's
    (a block number of 2 or more, then 0x50); a text, image or other file says so at any size."""
    path = tmp_path / "x.c3d"
    path.write_bytes(data)
    with pytest.raises(C3DError) as err:
        read_c3d(path)
    assert_our_words(err.value, path, problem)


def test_real_header_cut_short_is_truncated(tmp_path):
    raw = data_file("ezc3d_testfiles/Vicon.c3d").read_bytes()
    path = tmp_path / "vicon.c3d"
    path.write_bytes(raw[:300])
    with pytest.raises(C3DError) as err:
        read_c3d(path)
    assert_our_words(err.value, path, "truncated: 300 bytes, shorter than the 512-byte header")


def _cut(n):
    return lambda b: b[:n] if n >= 1 else b[:int(len(b) * n)]


def _put(at, new):
    return lambda b: b[:at] + new + b[at + len(new):]


def _zero_parameters(b):
    start = (b[0] - 1) * 512
    end = start + b[start + 2] * 512
    return b[:start + 4] + bytes(end - start - 4) + b[end:]


@pytest.mark.parametrize("rel, edit, problem", [
    # each was an ezc3d or py-c3d exception text before (iostream error, unpack requires a buffer, ...)
    (ART, _cut(20_000), "truncated: 969 frames announced, 16 whole frames stored and 288 bytes of a partial frame"),
    ("btk_samples/others__badParameterOffset.c3d", _cut(5120), "corrupt parameter section: parameter LABELS is 429"),
    ("btk_samples/sample01__Eb015pi.c3d", _cut(5120),
     "truncated: 450 frames announced but the file ends where its data section starts (byte 5120)"),
    ("c3dorg_samples/sample_13__Dance.c3d", _cut(5120), "truncated: 499 frames announced, 2 whole frames stored"),
    ("c3dorg_samples/sample_27__kyowadengyo.c3d", _cut(20480), "truncated: 152 frames announced, 71 whole frames"),
    ("c3dorg_samples/sample_11__evart.c3d", _cut(0.5), "truncated: "),
    ("btk_samples/sample02__sgi_real.c3d", _cut(0.5), "truncated: "),                 # MIPS: c3d package only
    ("btk_samples/others__MyCube.c3d", _put(539, b"\x01"),
     "unreadable: parameter S has element size 76 (expected -1, 1, 2 or 4); no valid POINT:RATE"),
    ("btk_samples/sample02__pc_real.c3d", _zero_parameters,
     "unreadable: no point channels (the header claims 36); the header's 64 analog values per frame differ"),
    ("btk_samples/sample02__pc_real.c3d", _put(515, b"\x00"),
     "not a C3D file, or a corrupt one (processor type 0 at byte 516, expected 84 Intel, 85 DEC or 86 MIPS)"),
    ("btk_samples/sample02__sgi_real.c3d", _put(300, b"\xff\x00"), "the header says 65280 events, more than its 18"),
])
def test_damaged_corpus_copies_say_what_is_wrong(tmp_path, rel, edit, problem):
    path = tmp_path / f"damaged_{Path(rel).name}"
    path.write_bytes(edit(data_file(rel).read_bytes()))
    with pytest.raises(C3DError) as err:
        read_c3d(path)
    assert_our_words(err.value, path, problem)


def test_garbage_in_the_data_section_is_still_read(tmp_path):
    raw = bytearray(data_file("btk_samples/sample02__pc_real.c3d").read_bytes())
    start = (raw[0] - 1) * 512 + raw[(raw[0] - 1) * 512 + 2] * 512
    raw[start + 100:start + 164] = np.random.default_rng(0).integers(0, 256, 64, dtype=np.uint8).tobytes()
    path = tmp_path / "noisy.c3d"
    path.write_bytes(bytes(raw))
    assert read_c3d(path).points.shape == read_c3d(data_file("btk_samples/sample02__pc_real.c3d")).points.shape


def test_unsupported_units_raise(tmp_path):
    import ezc3d

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = np.array([100.0])
    c["parameters"]["POINT"]["LABELS"]["value"] = ["a", "b"]
    c.add_parameter("POINT", "UNITS", ["in"])
    c["data"]["points"] = np.ones((4, 2, 5))
    c.write(str(tmp_path / "inch.c3d"))
    with pytest.raises(C3DError, match="unsupported POINT:UNITS 'in'"):
        read_c3d(tmp_path / "inch.c3d")


# --------------------------------------------------------------------------------------
# Gaps, units, residuals, rates, frame counts
# --------------------------------------------------------------------------------------
def test_dfki_gaps_are_nan_and_units_convert():
    path = data_file(DFKI)
    d = read_c3d(path)
    gaps = dict(zip(d.labels, np.round(100 * d.gap_fraction, 1)))
    assert gaps["thumb_tip"] == 8.2 and gaps["middle_tip"] == 1.3 and gaps["ring_tip"] == 0.7
    assert np.isnan(d.points[..., 0]).sum() == 613
    assert sum(v > 0 for v in gaps.values()) == 3
    raw = ezc3d_points_mm(path)
    assert np.array_equal(np.isnan(raw), np.isnan(d.points))
    np.testing.assert_allclose(d.points, raw * 0.001, rtol=0, atol=1e-12)
    assert d.units == "mm" and d.rate == 100.0 and d.n_frames == 6000
    assert np.allclose(np.diff(d.times), 0.01) and d.times[0] == 0.0
    sub = d.select(["thumb_tip", "hand_top"])
    assert sub.labels == ["thumb_tip", "hand_top"] and sub.points.shape == (6000, 2, 3)
    np.testing.assert_array_equal(sub.points[:, 0], d.points[:, d.index("thumb_tip")])
    with pytest.raises(C3DError, match="not in the trial"):
        d.select(["no_such_marker"])


def test_invalid_points_masked_even_where_c3d_keeps_stale_xyz():
    import c3d

    path = data_file("c3dorg_samples/sample_16__basketball.c3d")  # every point flagged invalid
    with open(path, "rb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        raw = np.array([p for _, p, _ in c3d.Reader(fh).read_frames()])
    assert (raw[..., 3] < 0).all() and np.abs(raw[..., :3]).max() > 0   # stale coordinates
    d = read_c3d(path, backend="c3d")
    assert np.isnan(d.points).all() and np.isnan(d.residuals).all()


def test_units_in_metres_file():
    path = data_file("c3dorg_samples/NexGen_Ergonomics__test1.c3d")
    d = read_c3d(path)
    assert d.units == "m"
    np.testing.assert_allclose(d.points, ezc3d_points_mm(path), rtol=0, atol=1e-12)  # no x0.001
    assert 0.5 < np.nanmax(np.abs(d.points)) < 5.0


def test_cm_file_written_and_read(tmp_path):
    import ezc3d

    pts = np.random.default_rng(1).uniform(-1, 1, (10, 3, 3))
    path = write_c3d(tmp_path / "cm.c3d", pts, ["a", "b", "c"], 50.0, units="cm")
    raw = ezc3d.c3d(str(path))
    assert raw["parameters"]["POINT"]["UNITS"]["value"] == ["cm"]
    np.testing.assert_allclose(raw["data"]["points"][:3].transpose(2, 1, 0), pts * 100, atol=1e-4)
    d = read_c3d(path)
    assert d.units == "cm"
    np.testing.assert_allclose(d.points, pts, rtol=0, atol=1e-7)


def test_ezc3d_residual_bytes_are_unswapped():
    import ezc3d

    path = data_file("btk_samples/sample01__Eb015pi.c3d")
    a, b = read_c3d(path, backend="ezc3d"), read_c3d(path, backend="c3d")
    np.testing.assert_allclose(a.residuals, b.residuals, rtol=0, atol=1e-9)
    raw = ezc3d.c3d(str(path))["data"]["meta_points"]["residuals"][0].T * 1e-3
    ok = ~np.isnan(a.residuals)
    assert not np.allclose(raw[ok], a.residuals[ok]), "ezc3d no longer swaps: simplify the reader"


def test_non_integer_rate_and_c3d_fallback():
    d = read_c3d(data_file("c3dorg_samples/sample_13__Dance.c3d"))
    assert d.backend == "c3d" and d.rate == 65.053345  # float32 65.0533447... shortest decimal
    assert d.n_frames == 499 and d.n_markers == 40


def test_optotrak_trusts_the_frames_actually_stored():
    path = data_file("ezc3d_testfiles/Optotrak.c3d")
    head = path.read_bytes()[:10]
    assert struct.unpack("<H", head[8:10])[0] == 1149   # the header's last frame
    for backend in ("ezc3d", "c3d"):
        d = read_c3d(path, backend=backend)
        assert d.n_frames == 29 and d.n_markers == 54


def test_kyowadengyo_point_count_follows_the_data():
    path = data_file("c3dorg_samples/sample_27__kyowadengyo.c3d")
    raw = ezc3d_points_mm(path)                        # POINT:USED = 12: wrong stride
    raw_step = np.nanmedian(np.linalg.norm(np.diff(raw, axis=0), axis=2))
    d = read_c3d(path)
    assert (d.n_markers, d.n_frames, d.first_frame) == (11, 152, 33)
    step = np.nanmedian(np.linalg.norm(np.diff(d.points, axis=0), axis=2)) * 1000
    assert step < 40 < 300 < raw_step                  # walking at 60 Hz vs garbage


def test_art_hands():
    d = read_c3d(data_file(ART))
    assert d.n_frames == 969 and d.rate == 60.0 and d.n_markers == 61 and d.units == "mm"
    assert all(o.startswith("Human4:") for o in d.original_labels)
    assert all(":" not in lab for lab in d.labels)
    assert d.labels[:2] == ["PELV", "LLSP"] and "RTTI" in d.labels
    assert d.descriptions[0] == "Pelvis"
    assert d.backend == "ezc3d"


def test_model_outputs_are_not_markers():
    d = read_c3d(data_file("btk_samples/others__parameterOverflow.c3d"))
    assert d.n_markers == 142 - 36
    assert not any(lab.endswith(("Angles", "Angle", "Force", "GRF", "Moment", "Power")) for lab in d.labels)


def test_events():
    d = read_c3d(data_file("ezc3d_testfiles/Qualisys.c3d"))
    assert [e[0] for e in d.events] == ["LHS", "RTO", "RHS", "LTO", "LHS", "RTO", "RHS"]
    assert d.events[0][1] == pytest.approx(3.59) and d.first_frame == 705
    assert d.times[0] <= d.events[0][1] <= d.events[-1][1] <= d.times[-1]
    walk = read_c3d(data_file("c3dorg_samples/Motion_Analysis_Corporation__Walk1.c3d"))
    assert len(walk.events) == 8 and {e[2] for e in walk.events} == {"LHS", "RHS", "LTO", "RTO"}


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------
LABEL = st.text("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_", min_size=1, max_size=12)


@st.composite
def trials(draw):
    f = draw(st.integers(1, 40))
    m = draw(st.integers(1, 12))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-1.9, 1.9, (f, m, 3))             # float32 keeps 1e-4 mm below 2 m
    gaps = rng.random((f, m)) < draw(st.sampled_from([0.0, 0.1, 0.5, 1.0]))
    pts[gaps] = np.nan
    labels = draw(st.lists(LABEL, min_size=m, max_size=m, unique=True))
    units = draw(st.sampled_from(["mm", "cm", "m"]))
    prefix = draw(st.sampled_from(["", "Sim", "Subject01:"]))
    rate = draw(st.one_of(st.integers(1, 10000).map(float), st.integers(1, 99999).map(lambda k: k / 100)))
    first = draw(st.integers(1, 5000))
    return pts, labels, units, prefix, rate, first


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(trials())
def test_write_read_round_trip(trial):
    pts, labels, units, prefix, rate, first = trial
    with tempfile.TemporaryDirectory() as tmp:
        path = write_c3d(Path(tmp) / "t.c3d", pts, labels, rate, units=units, prefix=prefix,
                         first_frame=first)
        d = read_c3d(path)
        assert os.listdir(tmp) == ["t.c3d"]
    assert np.array_equal(np.isnan(d.points), np.isnan(pts))
    if not np.isnan(pts).all():
        assert np.nanmax(np.abs(d.points - pts)) * 1000 <= 1e-4
    assert d.rate == rate and d.units == units and d.first_frame == first
    assert d.labels == labels
    pre = prefix.rstrip(":")
    assert d.original_labels == [f"{pre}:{lab}" if pre else lab for lab in labels]


def test_write_never_overwrites_unless_asked(tmp_path):
    pts = np.zeros((3, 2, 3))
    path = write_c3d(tmp_path / "t.c3d", pts, ["a", "b"], 100.0)
    before = path.read_bytes()
    with pytest.raises(FileExistsError):
        write_c3d(path, pts + 1, ["a", "b"], 100.0)
    assert path.read_bytes() == before
    write_c3d(path, pts + 1, ["a", "b"], 100.0, overwrite=True)
    assert read_c3d(path).points[0, 0, 0] == 1.0
    assert sorted(os.listdir(tmp_path)) == ["t.c3d"]   # no temporary files left


def test_write_metadata_round_trip(tmp_path):
    pts = np.ones((4, 2, 3)) * 0.5
    pts[1, 0] = np.nan
    path = write_c3d(tmp_path / "m.c3d", pts, ["a", "b"], 120.0, prefix="Sim",
                     descriptions=["first", "second"], events=[("Off", 0.02, "Left"), ("On", 0.01, "Right")])
    d = read_c3d(path)
    assert d.descriptions == ["first", "second"]
    assert d.events == [("On", 0.01, "Right"), ("Off", 0.02, "Left")]
    assert d.residuals[1, 0] != d.residuals[1, 0] and d.residuals[0, 0] == 0.0
    assert d.backend == "ezc3d" and read_c3d(path, backend="c3d").labels == ["a", "b"]


@pytest.mark.parametrize("kwargs, match", [
    (dict(units="inch"), "unsupported units"),
    (dict(labels=["a"]), "2 markers but 1 labels"),
    (dict(labels=["a", "a"]), "not unique"),
    (dict(labels=["a", " b"]), "surrounding spaces"),
    (dict(rate=0.0), "rate must be positive"),
    (dict(points=np.zeros((0, 2, 3))), "nothing to write"),
    (dict(points=np.zeros((3, 2))), "shape"),
])
def test_write_rejects_bad_input(tmp_path, kwargs, match):
    args = dict(points=np.zeros((3, 2, 3)), labels=["a", "b"], rate=100.0) | kwargs
    with pytest.raises(C3DError, match=match):
        write_c3d(tmp_path / "bad.c3d", args.pop("points"), args.pop("labels"), args.pop("rate"), **args)
    assert not any(tmp_path.iterdir())
