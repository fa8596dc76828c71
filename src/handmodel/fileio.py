"""Atomic, non-clobbering file output and lookup of shipped resources."""
from __future__ import annotations

import hashlib
import json
import os
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

_SHARE = Path("share") / "synergistic-hand-tracking"


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


@contextmanager
def atomic_path(path: str | os.PathLike, *, overwrite: bool = True, suffix: str = ".tmp"):
    """Yield a temporary path beside ``path``; when the block succeeds, the file written there is
    synced and moved into place (``os.replace``, or with ``overwrite=False`` a hard link, which fails
    atomically if the name exists: ``FileExistsError``). On any error the temporary file is removed
    and ``path`` is left as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not overwrite and path.exists():
        raise FileExistsError(f"{path}: exists and is never overwritten")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; outputs get the usual permissions
        yield Path(tmp)
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
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def atomic_write_bytes(path: str | os.PathLike, data: bytes, *, overwrite: bool = True) -> Path:
    """Write ``data`` to ``path`` through a temporary file and a rename (see :func:`atomic_path`)."""
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str, *, overwrite: bool = True) -> Path:
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


def schema_errors(doc, name: str) -> str | None:
    """The first violation of ``data_schema/<name>.schema.json`` as ``field a/b: message``, or None."""
    import jsonschema

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


def load_yaml(path, error_cls):
    """Parse a YAML file; unreadable or invalid YAML → ``error_cls(path, reason)``."""
    import yaml

    path = Path(path)
    try:
        return yaml.safe_load(path.read_text())
    except OSError as exc:
        raise error_cls(path, f"cannot read: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise error_cls(path, f"not valid YAML: {str(exc).splitlines()[0]}") from None
