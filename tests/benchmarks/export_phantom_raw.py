"""Writes the default phantom as raw arrays for the Rust criterion benches.

Usage: python tests/benchmarks/export_phantom_raw.py [OUT_DIR]   (default: target/bench-data)

Files: ``phantom.hdr`` (one line: nx ny nz sx sy sz ox oy oz ax ay az bx by bz — counts, then
metres: spacing, origin, entry A, target B), ``phantom.hu.i16`` and ``phantom.labels.u8``
(little-endian, [z, y, x] order, x fastest).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

import dhg


def main() -> None:
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "target/bench-data")
    out.mkdir(parents=True, exist_ok=True)
    p = dhg.default_phantom()
    v = p.volume
    nz, ny, nx = v.shape
    fields = [nx, ny, nz, *v.spacing_m, *v.origin_m, *p.path.entry_m, *p.path.target_m]
    (out / "phantom.hdr").write_text(" ".join(repr(float(f)) if i > 2 else str(f) for i, f in enumerate(fields)))
    v.hu().astype("<i2").tofile(out / "phantom.hu.i16")
    v.labels().astype(np.uint8).tofile(out / "phantom.labels.u8")
    print(f"wrote {v} to {out}")


if __name__ == "__main__":
    main()
