"""Seal a schema-1 synergy bundle (manifest not hashed) as schema 2, keeping its arrays bit for bit.

Used once for the shipped ``models/synergies/fingerfist-1.0.0.npz``: refitting it with
``synergy fit`` (the command in docs/synergy.md) reproduces the arrays only to ~1e-13 (the
eigen-solver's rounding), and the tracker's reported numbers were measured with the stored arrays.
The tool refuses a file whose arrays do not match the ``arrays_sha256`` its manifest records, so a
tampered bundle is never blessed; it writes to a new folder and never overwrites.

Run: .venv/bin/python tools/reseal_bundle.py models/synergies/fingerfist-1.0.0.npz -o /tmp/resealed
"""
from __future__ import annotations

import argparse
import io
import json
import sys
from pathlib import Path

import numpy as np

from handmodel.fileio import atomic_write_bytes
from synergy.bundle import ARRAY_NAMES, SCHEMA_VERSION, arrays_sha256, manifest_sha256, read_bundle
from synergy.errors import BundleError


def reseal(src: Path, out_dir: Path) -> Path:
    """Write ``out_dir/<src name>``: the same arrays, the manifest at :data:`SCHEMA_VERSION` with its hash."""
    with np.load(src, allow_pickle=False) as z:
        arrays = {n: z[n] for n in ARRAY_NAMES}
        manifest = json.loads(str(z["manifest"][()]))
    if manifest.get("schema_version") != 1:
        raise BundleError(src, f"schema_version {manifest.get('schema_version')}: only schema-1 bundles are resealed")
    if arrays_sha256(arrays) != manifest.get("arrays_sha256"):
        raise BundleError(src, "arrays do not match the manifest's arrays_sha256: refusing to seal a modified file")
    manifest["schema_version"] = SCHEMA_VERSION
    manifest["manifest_sha256"] = manifest_sha256(manifest)
    buf = io.BytesIO()
    np.savez(buf, **arrays, manifest=np.array(json.dumps(manifest, indent=1)))
    out = atomic_write_bytes(out_dir / src.name, buf.getvalue(), overwrite=False)
    read_bundle(out)  # the sealed file passes every check of the reader
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bundles", nargs="+", type=Path)
    ap.add_argument("-o", "--out", type=Path, required=True, help="output folder (files are never overwritten)")
    args = ap.parse_args()
    try:
        for src in args.bundles:
            print(reseal(src, args.out))
    except (BundleError, FileExistsError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
