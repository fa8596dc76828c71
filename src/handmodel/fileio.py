"""Atomic, non-clobbering file output and lookup of shipped resources."""
from __future__ import annotations

import errno
import hashlib
import json
import math
import os
import sys
import tempfile
import zipfile
from contextlib import contextmanager
from pathlib import Path

_SHARE = Path("share") / "synergistic-hand-tracking"


def plain_values(value):
    """``value`` with numpy scalars and arrays, tuples and paths turned into YAML's plain types
    (the one conversion of our YAML writers: hand files, subject calibrations).

    >>> import numpy as np
    >>> plain_values({"a": np.float64(1.5), 2: (np.int64(3), np.array([True]))})
    {'a': 1.5, '2': [3, [True]]}
    """
    import numpy as np  # here, not at the top: this module serves `--help` too

    if isinstance(value, dict):
        return {str(k): plain_values(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain_values(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain_values(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value


def resource_dir(kind: str) -> Path:
    """Folder of a shipped resource kind (``models``, ``data_schema``).

    Looks in the source checkout first (``<repo>/models``), then in the installed data
    files (``<prefix>/share/synergistic-hand-tracking/<kind>``).
    """
    checkout = Path(__file__).resolve().parents[2] / kind
    if checkout.is_dir():
        return checkout
    for prefix in (sys.prefix, sys.base_prefix):
        cand = Path(prefix) / _SHARE / kind
        if cand.is_dir():
            return cand
    return checkout


def models_dir() -> Path:
    return resource_dir("models")


def schema_path(name: str) -> Path:
    """Path of ``data_schema/<name>.schema.json``."""
    return resource_dir("data_schema") / f"{name}.schema.json"


def _os_error(exc: OSError, path) -> OSError:
    """The same OS error, naming ``path`` (the output the user asked for, not a temporary name)."""
    return OSError(exc.errno, exc.strerror or str(exc), str(path))


def check_output(path: str | os.PathLike, *, overwrite: bool = False, folder: bool = False) -> Path:
    """Fail now, not after the long work, if ``path`` cannot be written.

    Checks that ``path`` is not an existing folder (or, with ``folder=True``, not an existing
    file), is not there already unless ``overwrite``, and that the folder it goes into can
    take a new file: a probe file is created and removed there, which also catches a
    read-only file system for root (who passes every permission check), and the file system
    has a free block (an empty probe fits on a full disk, the output would not).

    Raises
    ------
    FileExistsError, IsADirectoryError, NotADirectoryError, OSError
        Naming ``path`` (``err.filename``) and the problem (``err.strerror``).
    """
    path = Path(path)
    if folder:
        if path.exists() and not path.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, "exists and is not a folder", str(path))
        target = path
    else:
        if path.is_dir():
            raise IsADirectoryError(errno.EISDIR, "is a folder, not a file", str(path))
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path}: exists and is never overwritten")
        target = path.parent
    probe_in = target
    while not probe_in.exists():  # the nearest folder that exists must let us create the rest
        probe_in = probe_in.parent
    if not probe_in.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, f"{probe_in} is not a folder", str(path))
    try:
        fd, probe = tempfile.mkstemp(prefix=".write-check.", dir=probe_in)
        os.close(fd)
        os.unlink(probe)
        st = os.statvfs(probe_in) if hasattr(os, "statvfs") else None
    except OSError as exc:
        if exc.errno == errno.ENOENT:
            # "no such file" of a folder that is there: it takes no new files (/proc, /sys)
            raise OSError(errno.ENOENT, f"cannot be created there: the folder {probe_in} exists but takes no new "
                                        "files (a virtual file system such as /proc or /sys?)", str(path)) from None
        raise _os_error(exc, path) from None
    # root may use the blocks reserved for it; f_blocks == 0 is a file system that keeps no count
    if st is not None and st.f_blocks and not (st.f_bfree if os.geteuid() == 0 else st.f_bavail):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
    return path


def _verify_default(tmp: Path, final: Path, empty_ok: bool = False) -> None:
    """What any output must satisfy: not empty (unless a caller's check knows better), and a
    ``.npz`` must be a sound zip."""
    if not empty_ok and tmp.stat().st_size == 0:
        raise OSError(errno.EIO, "the write produced an empty file", str(final))
    if final.suffix.lower() == ".npz":
        try:
            with zipfile.ZipFile(tmp) as zf:
                bad = zf.testzip()
        except (zipfile.BadZipFile, OSError) as exc:
            raise OSError(errno.EIO, f"the written archive is unreadable ({exc})", str(final)) from None
        if bad is not None:
            raise OSError(errno.EIO, f"the written archive has a corrupt member {bad}", str(final))


@contextmanager
def atomic_path(path: str | os.PathLike, *, overwrite: bool = True, suffix: str = ".tmp", verify=None):
    """Yield a temporary path beside ``path``; when the block succeeds, the file written there is
    checked, synced and moved into place (``os.replace``, or with ``overwrite=False`` a hard link,
    which fails atomically if the name exists: ``FileExistsError``). On any error the temporary
    file is removed and ``path`` is left as it was.

    The check is: not empty, a ``.npz`` a sound zip, and ``verify(tmp)`` if given (raise to
    refuse the file) -- a writer that fails silently on a full disk (ezc3d does) must not get a
    truncated file published. OS errors come out naming ``path``, not the temporary name.
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(errno.EISDIR, "is a folder, not a file", str(path))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _os_error(exc, path) from None
    if not overwrite and path.exists():
        raise FileExistsError(f"{path}: exists and is never overwritten")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    except OSError as exc:
        raise _os_error(exc, path) from None
    os.close(fd)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; outputs get the usual permissions
        try:
            yield Path(tmp)
            _verify_default(Path(tmp), path, empty_ok=verify is not None)
            if verify is not None:
                verify(Path(tmp))
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
            if overwrite:
                os.replace(tmp, path)
            else:
                try:
                    os.link(tmp, path)
                except FileExistsError:
                    raise FileExistsError(f"{path}: exists and is never overwritten") from None
                os.unlink(tmp)
        except FileExistsError:
            raise
        except OSError as exc:
            if exc.filename == str(path):
                raise
            raise _os_error(exc, path) from None
    finally:
        if os.path.exists(tmp):
            try:
                os.unlink(tmp)
            except OSError:
                pass  # a read-only remount after the write: nothing more can be done


def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, overwrite: bool = True) -> Path:
    """Write ``data`` to ``path`` through a temporary file and a rename (see :func:`atomic_path`);
    the temporary file is read back and compared before it is published."""

    def same(tmp: Path) -> None:
        if tmp.stat().st_size != len(data) or tmp.read_bytes() != data:
            raise OSError(errno.EIO, "the written file differs from the data (short write)", str(path))

    with atomic_path(path, overwrite=overwrite, verify=same) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str, *, overwrite: bool = True) -> Path:
    """Write UTF-8 ``text`` like :func:`atomic_write_bytes`."""
    return atomic_write_bytes(path, text.encode("utf-8"), overwrite=overwrite)


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while True:
            b = fh.read(chunk)
            if not b:
                break
            h.update(b)
    return h.hexdigest()


def arrays_sha256(arrays, names) -> str:
    """SHA-256 of ``arrays[name]`` for each of ``names`` in that order: per array a header
    ``name\\0dtype\\0shape\\0`` and its little-endian C-order bytes (the seal of every sealed ``.npz``:
    synergy bundles, detectors). Arrays not named are not covered.

    >>> import numpy as np
    >>> a = {"x": np.arange(3, dtype="<f8"), "y": np.array(["a", "b"])}
    >>> h = arrays_sha256(a, ("x", "y"))
    >>> arrays_sha256({"y": a["y"], "x": a["x"], "z": 0}, ("x", "y")) == h  # dict order, extra keys
    True
    >>> arrays_sha256({**a, "x": a["x"].astype(">f8")}, ("x", "y")) == h  # byte order of the machine
    True
    >>> b = a["x"].copy(); b.view(np.uint8)[0] ^= 1
    >>> arrays_sha256({**a, "x": b}, ("x", "y")) == h, arrays_sha256(a, ("y", "x")) == h
    (False, False)
    """
    import numpy as np  # here, not at the top: this module serves `--help` too

    h = hashlib.sha256()
    for name in names:
        a = np.asarray(arrays[name])
        a = np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("<"))
        h.update(f"{name}\0{a.dtype.str}\0{a.shape}\0".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def manifest_sha256(manifest: dict) -> str:
    """SHA-256 of a manifest without its own ``manifest_sha256`` field, as canonical JSON (keys sorted,
    no spaces, UTF-8). The manifest holds :func:`arrays_sha256`, so this one hash seals the whole file.

    >>> m = {"b": [1, 2.5], "a": "é", "arrays_sha256": "00"}
    >>> h = manifest_sha256(m)
    >>> manifest_sha256(dict(reversed(m.items()))) == manifest_sha256({**m, "manifest_sha256": h}) == h
    True
    >>> manifest_sha256({**m, "b": [1, 2.6]}) == h
    False
    """
    body = {k: v for k, v in manifest.items() if k != "manifest_sha256"}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _first_nan(doc, at=(), bad=math.isnan):
    """Path and value of the first NaN (or other float ``bad`` accepts) in a parsed document, or None."""
    if isinstance(doc, float) and bad(doc):
        return at, doc
    if isinstance(doc, dict):
        items = doc.items()
    elif isinstance(doc, (list, tuple)):
        items = enumerate(doc)
    else:
        return None
    for k, v in items:
        found = _first_nan(v, (*at, k), bad)
        if found:
            return found
    return None


def first_non_finite(doc):
    """``(path, value)`` of the first NaN or infinity in a parsed JSON/YAML document, or None
    (``json.loads`` reads ``NaN`` and ``Infinity``, which no JSON-schema bound catches)."""
    return _first_nan(doc, bad=lambda x: not math.isfinite(x))


def schema_errors(doc, name: str) -> str | None:
    """The first violation of ``data_schema/<name>.schema.json`` as ``field a/b: message``, or None.

    A NaN is a violation in any schema: JSON-schema bounds cannot catch it (every comparison
    with NaN is false) and YAML writes it as plain ``.nan``. Infinities are left to the bounds
    (``.inf`` is over any ``maximum``; a hand model's joint limits may be infinite).
    """
    import jsonschema

    bad = _first_nan(doc)
    if bad:
        return f"field {'/'.join(map(str, bad[0])) or '(top level)'}: {bad[1]} is not a number"

    schema = json.loads(schema_path(name).read_text())
    errs = sorted(jsonschema.Draft202012Validator(schema).iter_errors(doc), key=lambda e: list(e.absolute_path))
    if not errs:
        return None
    e = errs[0]
    return f"field {'/'.join(str(p) for p in e.absolute_path) or '(top level)'}: {e.message}"


def resolve_model_file(kind: str, name_or_path, error_cls, what: str) -> Path:
    """A shipped ``models/<kind>/<name>.yaml`` by name, or a YAML file by path; ``error_cls(where,
    reason)`` for a missing one, listing the shipped names."""
    p = Path(name_or_path)
    if p.suffix not in (".yaml", ".yml"):
        cand = models_dir() / kind / f"{name_or_path}.yaml"
        if not cand.exists():
            known = sorted(q.stem for q in (models_dir() / kind).glob("*.yaml"))
            raise error_cls(name_or_path, f"no such {what} (known: {', '.join(known) or 'none'})")
        p = cand
    if not p.exists():
        raise error_cls(p, "file not found")
    return p


#: Largest YAML file read (metadata, task maps, models are a few KiB): a bigger one is refused
#: before parsing, so parsing time and memory stay bounded.
MAX_YAML_BYTES = 4 << 20


def _no_alias_loader():
    import yaml

    class NoAliasLoader(yaml.SafeLoader):
        """SafeLoader that refuses aliases: a 400-byte "billion laughs" document of nested
        aliases expands to gigabytes (measured: 49-103 s, > 3.9 GB). Our files never need them."""

        def compose_node(self, parent, index):
            if self.check_event(yaml.events.AliasEvent):
                event = self.peek_event()
                raise yaml.composer.ComposerError(
                    None, None, f"YAML aliases (*{event.anchor}) are not allowed", event.start_mark)
            return super().compose_node(parent, index)

    return NoAliasLoader


def _load_no_alias(yaml, text):
    """The document, refusing aliases: with libyaml (PyYAML's C parser, ~9× faster: a hand model
    file 0.16 → 0.02 s) its events are checked first — streamed, so aliases are never expanded —,
    else by the pure-Python :func:`_no_alias_loader`."""
    fast = getattr(yaml, "CSafeLoader", None)
    if fast is None:
        return yaml.load(text, Loader=_no_alias_loader())  # noqa: S506 - a SafeLoader subclass
    for event in yaml.parse(text, Loader=fast):
        if isinstance(event, yaml.AliasEvent):
            raise yaml.composer.ComposerError(None, None, f"YAML aliases (*{event.anchor}) are not allowed",
                                              event.start_mark)
    return yaml.load(text, Loader=fast)  # noqa: S506 - libyaml's SafeLoader


def parse_yaml(data: bytes, where, error_cls):
    """Parse YAML bytes: UTF-8 only, no aliases, at most :data:`MAX_YAML_BYTES`.

    Returns the document; anything else is ``error_cls(where, reason)`` with a one-line reason.
    ``yaml.YAMLError`` is not caught here if the caller wants its own message: see
    :func:`load_yaml`.
    """
    import yaml

    if len(data) > MAX_YAML_BYTES:
        raise error_cls(where, f"{len(data)} bytes, too large for a YAML file here (limit {MAX_YAML_BYTES})")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error_cls(where, f"not UTF-8 text (byte {data[exc.start]:#04x} at offset {exc.start})") from None
    try:
        return _load_no_alias(yaml, text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        hint = " (quote globs and other values that start with '*')" if "alias" in str(exc) else ""
        raise error_cls(where, f"not valid YAML{at}: {problem}{hint}") from None
    except RecursionError:
        raise error_cls(where, "not valid YAML: nested too deeply") from None


def read_limited(path, limit: int, error_cls) -> bytes:
    """The bytes of a file of at most ``limit`` bytes; a bigger, missing or unreadable file is
    ``error_cls(path, reason)``."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            data = fh.read(limit + 1)
    except FileNotFoundError:
        raise error_cls(path, "file not found") from None
    except IsADirectoryError:
        raise error_cls(path, "is a folder, not a file") from None
    except OSError as exc:
        raise error_cls(path, f"cannot read: {exc.strerror or exc}") from None
    if len(data) > limit:
        raise error_cls(path, f"larger than {limit} bytes, too large for this kind of file")
    return data


def load_yaml(path, error_cls):
    """Parse a YAML file (see :func:`parse_yaml`); unreadable, non-UTF-8, oversized or invalid
    YAML, or YAML with aliases → ``error_cls(path, reason)``."""
    path = Path(path)
    return parse_yaml(read_limited(path, MAX_YAML_BYTES, error_cls), path, error_cls)


#: Largest total of the uncompressed arrays of a ``.npz`` read by :func:`load_npz` by default.
MAX_NPZ_BYTES = 256 << 20


class NpzArrays(dict):
    """``{name: ndarray}`` read by :func:`load_npz`; usable where ``np.load``'s ``NpzFile`` was
    (``.files``, ``z[name]``, ``with``)."""

    @property
    def files(self) -> list[str]:
        return list(self)

    def __enter__(self) -> "NpzArrays":
        return self

    def __exit__(self, *exc) -> None:
        return None


def load_npz(path, error_cls, max_bytes: int = MAX_NPZ_BYTES, what: str = ".npz archive") -> NpzArrays:
    """The arrays of a ``.npz`` file, checked before anything is decompressed.

    A 1.9 MB archive can unpack to 2 GB, so the zip members' declared sizes and each ``.npy``
    header (dtype and shape) are checked against ``max_bytes`` first; object arrays (pickles)
    are refused; a file that is not a zip (say a ``.npy`` renamed) is refused by name.

    Returns
    -------
    NpzArrays
        ``{name: ndarray}`` (names without ``.npy``).

    Raises
    ------
    error_cls
        ``error_cls(path, "not a readable <what> (<why>)")``.
    """
    import numpy as np
    from numpy.lib import format as npformat

    path = Path(path)

    def bad(why: str):
        return error_cls(path, f"not a readable {what} ({why})")

    try:
        with open(path, "rb") as fh:
            magic = fh.read(4)
        if magic[:4] != b"PK\x03\x04" and magic[:4] != b"PK\x05\x06":
            kind = "a .npy array" if magic == b"\x93NUM" else "not a zip archive"
            raise bad(f"the file is {kind}")
        with zipfile.ZipFile(path) as zf:
            members = zf.infolist()
            declared = sum(m.file_size for m in members)
            if declared > max_bytes:
                raise bad(f"unpacks to {declared} bytes, over the limit of {max_bytes}")
            out, total = NpzArrays(), 0
            for m in members:
                if not m.filename.endswith(".npy"):
                    raise bad(f"member {m.filename!r} is not a .npy array")
                with zf.open(m) as fh:
                    version = npformat.read_magic(fh)
                    # version 3.0 differs from 2.0 only in the header's text encoding
                    read_header = npformat.read_array_header_1_0 if version == (1, 0) else npformat.read_array_header_2_0
                    shape, _, dtype = read_header(fh)
                    if dtype.hasobject:
                        raise bad(f"{m.filename}: object arrays (pickles) are never loaded")
                    n = dtype.itemsize * int(np.prod(shape, dtype=object))
                    total += n
                    if total > max_bytes or n > m.file_size:
                        raise bad(f"{m.filename}: array of {n} bytes "
                                  f"{'over the limit' if total > max_bytes else 'larger than its member'}")
            for m in members:
                with zf.open(m) as fh:
                    out[m.filename[:-4]] = npformat.read_array(fh, allow_pickle=False)
            return out
    except error_cls:
        raise
    except FileNotFoundError:
        raise error_cls(path, "file not found") from None
    except OSError as exc:
        raise error_cls(path, f"cannot read: {exc.strerror or exc}") from None
    except (zipfile.BadZipFile, ValueError, EOFError, NotImplementedError) as exc:
        raise bad(str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None
