"""A short synthetic dataset's records, saved, to check that a refactor of the core drills the same
attempts bit for bit: run it before and after the change with different outputs, then compare.

    python tests/benchmarks/records_fingerprint.py before.npy      # on the old build
    python tests/benchmarks/records_fingerprint.py after.npy --compare before.npy

``--subjects N --voxel-mm 0.5`` drills more attempts (N experts and N novices) on the finer phantom.
"""

from __future__ import annotations

import argparse

import numpy as np

import dhg
from dhg.data.synth import synthesize


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", help="where to save the records (.npy)")
    p.add_argument("--compare", help="records saved earlier: exit 1 unless they are identical")
    p.add_argument("--subjects", type=int, default=1, help="experts, and as many novices (default 1)")
    p.add_argument("--voxel-mm", type=float, default=1.0, help="the phantom's voxel (mm, default 1)")
    args = p.parse_args()
    phantom = dhg.femur(seed=0, voxel_m=args.voxel_mm * 1e-3)
    episodes, _ = synthesize(
        phantom.volume, phantom.path, subjects=args.subjects, attempts=1, novices=args.subjects, seed=11
    )
    records = np.concatenate([e.records for e in episodes])
    np.save(args.out, records)
    print(f"{records.shape[0]} records, sum {float(records.sum())!r}")
    if args.compare:
        before = np.load(args.compare)
        same = before.shape == records.shape and np.array_equal(before, records)
        print("identical" if same else "DIFFERENT")
        raise SystemExit(0 if same else 1)


if __name__ == "__main__":
    main()
