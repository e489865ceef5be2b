"""Python-side benchmarks of the bone volume (the same workloads as the criterion benches, so the
difference is the FFI cost), plus building the phantom and session memory.

Usage: python tests/benchmarks/bench_volume.py      (prints a Markdown table; ~20 s)
"""

from __future__ import annotations

import platform
import statistics
import time

import numpy as np

import dhg
from dhg.operators.scripted import straight_line_drill


def timed(fn, repeat: int) -> list[float]:
    out = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return out


def main() -> None:
    rows: list[tuple[str, str, str]] = []
    builds = timed(lambda: dhg.femur(seed=0), 3)
    rows.append(("build the phantom (0.5 mm, 199×125×247)", f"{statistics.median(builds):.2f} s", "≤ 3 s"))
    p = dhg.default_phantom()
    vol, path = p.volume, p.path
    centre = path.point_at([1.75e-3])[0]
    assert vol.layer_at(centre)[0] == dhg.Layer.CORTICAL
    for radius_mm in (1.25, 2.5, 4.0):
        bone = vol.drill()
        per_call = []
        for i in range(2000):
            if i % 200 == 0:
                bone.reset()
            t = time.perf_counter()
            bone.remove(centre, radius_mm * 1e-3, 1200.0, 1e-3)
            per_call.append(time.perf_counter() - t)
        rows.append(
            (
                f"one removal call from Python, r = {radius_mm} mm, cortical",
                f"{np.median(per_call) * 1e6:.1f} µs (p99 {np.percentile(per_call, 99) * 1e6:.1f})",
                "≤ 20 µs at 2.5 mm (core)",
            )
        )
    bone = vol.drill()
    t = time.perf_counter()
    run = straight_line_drill(bone, path)
    drill_s = time.perf_counter() - t
    rows.append((f"scripted drill of the whole path ({run.ticks} ticks of 1 ms)", f"{drill_s:.3f} s", "—"))
    xr = timed(bone.xray, 20)
    rows.append(("three X-ray views of the drilled session", f"{statistics.median(xr) * 1e3:.2f} ms", "≤ 50 ms"))
    rows.append(
        (
            "session memory after drilling the path (2.5 mm drill)",
            f"{bone.memory_bytes / 1e3:.0f} kB ({bone.drilled_bricks} bricks used)",
            "≤ 1 MB",
        )
    )
    wide = vol.drill()
    straight_line_drill(wide, path, radius_m=2.5e-3)
    rows.append(
        (
            "session memory after drilling the path (5 mm burr)",
            f"{wide.memory_bytes / 1e3:.0f} kB ({wide.drilled_bricks} bricks used)",
            "≤ 1 MB",
        )
    )
    rows.append(("shared volume", f"{vol.memory_bytes / 1e6:.1f} MB", "—"))
    print(f"machine: {platform.machine()}, {platform.processor() or 'cpu'}, python {platform.python_version()}")
    print("| workload | result | target |\n|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]} |")


if __name__ == "__main__":
    main()
