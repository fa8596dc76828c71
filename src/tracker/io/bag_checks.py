"""Checks of a bag file's own structure before a reader trusts it: a ROS1 bag's index records and
the chunks they point at against the file's size (what they declare is allocated before it is read),
a ROS2 ``.db3``'s page count against its size. They read only headers and need no extra.
"""
from __future__ import annotations

import struct
from pathlib import Path

from ..errors import RecordingError
from .base import ROS1_MAGIC, SQLITE_MAGIC, looks_like


def _head_and_size(path: Path, n: int) -> tuple[bytes, int]:
    """The first ``n`` bytes of a file and its size (what the completeness checks compare)."""
    try:
        with open(path, "rb") as fh:
            return fh.read(n), fh.seek(0, 2)
    except OSError as exc:
        raise RecordingError(path, f"cannot read: {exc.strerror or exc}") from None


def check_sqlite_complete(path: Path) -> None:
    """Refuse a cut SQLite file: its header gives the database size in pages, and SQLite reads the
    pages missing past the end of a truncated file as zeros (depth frames would silently end in
    zeros)."""
    head, size = _head_and_size(path, 100)
    if len(head) < 100 or not head.startswith(SQLITE_MAGIC):
        return  # not SQLite at all: the reader says so
    page = struct.unpack(">H", head[16:18])[0]
    page = 65536 if page == 1 else page
    pages, change, valid_for = struct.unpack(">I", head[28:32])[0], head[24:28], head[92:96]
    if change == valid_for and pages and size < pages * page:
        raise RecordingError(path, f"truncated: the SQLite header says {pages * page} bytes, the file has {size}")


def check_ros1_complete(path: Path) -> int | None:
    """Refuse a ROS1 bag whose index is missing, naming why: its file header says where the index
    starts (``index_pos``), 0 while the recorder has not closed the file, past the end when the file
    was cut short (a copy or download that stopped). The reader's own error ("Bag index looks
    damaged: Header could not be read") does not tell a user either. Returns ``index_pos`` (None when
    the file is too short to tell or its header is damaged: the reader then says so)."""
    head, size = _head_and_size(path, 4096)
    if not head.startswith(ROS1_MAGIC):
        # the reader's error is its decoder's (a PNG renamed .bag: "'utf-8' codec can't decode byte 0x89")
        raise RecordingError(path, f"not a ROS1 bag: it does not start with {ROS1_MAGIC.strip().decode()!r} "
                                   f"({looks_like(head)})")
    if len(head) < len(ROS1_MAGIC) + 4:
        return  # too short to tell: the reader says so
    k = len(ROS1_MAGIC)
    hlen = struct.unpack("<I", head[k:k + 4])[0]
    fields = _record_fields(head[k + 4:k + 4 + hlen])
    if fields.get(b"op") != b"\x03" or len(fields.get(b"index_pos", b"")) != 8:
        return  # a damaged header: the reader says so
    index_pos = struct.unpack("<Q", fields[b"index_pos"])[0]
    if index_pos == 0:
        raise RecordingError(path, "unfinished: the recorder never wrote the bag's index (it stopped before "
                                   "closing the file); rebuild it with `rosbag reindex` (ROS1)")
    if index_pos >= size:
        raise RecordingError(path, f"cut short: the bag's index starts at byte {index_pos}, the file ends at "
                                   f"{size} (copy it again, or rebuild the index with `rosbag reindex`)")
    check_ros1_records(path, index_pos, size)
    return index_pos


def _record_fields(header: bytes) -> dict:
    """A ROS1 record header's ``name=value`` fields (each behind its u32 length)."""
    pos, fields = 0, {}
    while pos + 4 <= len(header):
        flen = struct.unpack("<I", header[pos:pos + 4])[0]
        name, _, value = header[pos + 4:pos + 4 + flen].partition(b"=")
        fields[name] = value
        pos += 4 + flen
    return fields


#: A ROS1 record header holds a few fields (a connection's, its message definition: a few kB); a
#: longer one is a damaged length, not read into memory.
_MAX_RECORD_HEADER = 1 << 24


def check_ros1_records(path: Path, index_pos: int, size: int) -> None:
    """Refuse a ROS1 bag whose index records, or the chunks they point at, declare lengths past the end
    of the file. The reader allocates what a record declares before it reads it: one length field set
    to 0xFFFFFFF0 made it ask for 4 GB (a MemoryError, or the machine's memory) instead of saying
    which record is damaged."""
    chunks = []
    try:
        with open(path, "rb") as fh:
            def record(pos, what):
                fh.seek(pos)
                raw = fh.read(4)
                hlen = struct.unpack("<I", raw)[0] if len(raw) == 4 else None
                if hlen is not None and hlen > _MAX_RECORD_HEADER:
                    raise RecordingError(path, f"{damage(what)} at byte {pos} declares a header of {hlen} bytes "
                                               f"(a ROS record's header is a few kB)")
                if hlen is None or pos + 8 + hlen > size:
                    raise RecordingError(path, f"{damage(what)} at byte {pos} declares a header of "
                                               f"{hlen if hlen is not None else '?'} bytes, past the file's end at {size}")
                header = fh.read(hlen)
                raw = fh.read(4)
                dlen = struct.unpack("<I", raw)[0] if len(raw) == 4 else None
                end = pos + 8 + hlen + (dlen or 0)
                if dlen is None or end > size:
                    raise RecordingError(path, f"{damage(what)} at byte {pos} declares "
                                               f"{dlen if dlen is not None else '?'} bytes of data, past the file's "
                                               f"end at {size}")
                return _record_fields(header), end

            def damage(what):
                # the index is the file's last part: a copy that stopped inside it looks the same
                return (f"damaged or cut short inside its index (from byte {index_pos}): the record"
                        if what == "index" else "damaged: the chunk")

            pos = index_pos
            while pos < size:
                fields, pos = record(pos, "index")
                if fields.get(b"op") == b"\x06" and len(fields.get(b"chunk_pos", b"")) == 8:
                    chunks.append(struct.unpack("<Q", fields[b"chunk_pos"])[0])
            for chunk_pos in chunks:
                if chunk_pos >= index_pos:
                    raise RecordingError(path, f"damaged: a chunk said to start at byte {chunk_pos}, inside the index")
                fields, end = record(chunk_pos, "chunk")
                if fields.get(b"op") != b"\x05":
                    raise RecordingError(path, f"damaged: the index points at a chunk at byte {chunk_pos}, but the "
                                               "record there is not a chunk")
                # a chunk is followed by its index data records (op 0x04): anything else there means
                # the chunk's declared size is wrong, which rosbags would read past without a word
                try:
                    follows = record(end, "chunk")[0] if end < index_pos else {}
                except RecordingError:
                    follows = {}
                if follows.get(b"op") != b"\x04":
                    raise RecordingError(path, f"damaged: the chunk at byte {chunk_pos} declares a size that ends at "
                                               f"byte {end}, where no index data record starts (a wrong chunk size)")
    except OSError as exc:
        raise RecordingError(path, f"cannot read: {exc.strerror or exc}") from None
