"""What a trainee's page costs the browser that draws it (issue 23): Chromium's CPU (its GPU
process, where SwiftShader draws WebGL in software, and its renderer, where the page's script
runs) and the WebGL draw calls a second, while the virtual trainee holds the stylus before the
bone, drills 15 mm in, then holds it still in the bone. Alternates the viewer's lighting (plain
lights, no shadows, no environment map) with viser's defaults (an HDR environment map and
shadow-casting lights), each over a fresh server, viewer and browser.

    python tests/benchmarks/bench_browser.py --rounds 2

Prints one line per phase and run, then the medians per variant and the ratios (ours / viser's).
A lab PC with a GPU draws the same page in hardware; this is the software (no-GPU) case, as in
headless Chromium on CI and on our VMs.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dhg.live.client import TraineeClient  # noqa: E402
from dhg.live.process import free_port  # noqa: E402
from dhg.view import Viewer, pages  # noqa: E402
from dhg.view.browser import chromium, drawn_canvas, wait_for  # noqa: E402
from support import Stylus, entry, serve  # noqa: E402

COUNT_DRAWS = """
window.__dhgDraws = 0;
for (const C of [WebGL2RenderingContext, WebGLRenderingContext]) {
  for (const fn of ['drawElements', 'drawArrays', 'drawElementsInstanced', 'drawArraysInstanced']) {
    const o = C.prototype[fn];
    if (o) C.prototype[fn] = function (...a) { window.__dhgDraws++; return o.apply(this, a); };
  }
}"""


def chromium_cpu_s(kind: str) -> float:
    """CPU seconds (user + system) of every Chromium process whose command line holds ``kind``."""
    total = 0
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
        except OSError:
            continue
        if "chrom" in stat[stat.index("(") + 1 : stat.rindex(")")] and kind in cmd:
            fields = stat[stat.rindex(")") + 2 :].split()
            total += int(fields[11]) + int(fields[12])
    return total / os.sysconf("SC_CLK_TCK")


@contextmanager
def viser_defaults():
    """The page as viser lights it by default (what the viewer turned off)."""
    original = pages._viser_server

    def default_lit(host: str, port: int, label: str) -> Any:
        server = original(host, port, label)
        server.scene.configure_environment_map("city")
        server.scene.configure_default_lights(True, cast_shadow=True)
        return server

    pages._viser_server = default_lit
    try:
        yield
    finally:
        pages._viser_server = original


def one_run(variant: str, hold_s: float) -> list[dict[str, Any]]:
    proc, endpoint = serve("--idle-timeout", "2.0")
    rows = []
    try:
        with TraineeClient(endpoint, "bench-1") as c, chromium() as browser:
            a, d, q = entry(c)
            hand = Stylus(c, q)
            viewer = Viewer(endpoint, port=free_port(), session_id="bench-1")
            try:
                hand.move(np.array([a - d * 3e-3]))
                browser.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument", {"source": COUNT_DRAWS})
                browser.get(viewer.url)
                wait_for(lambda: drawn_canvas(browser), 180, "the bone drawn")
                time.sleep(hold_s)  # the page's start settles (a benchmark, not a test)
                page = viewer.pages["bench-1"]
                phases = (
                    ("held before the bone", None),
                    ("drilling 15 mm", a + d * np.linspace(-3e-3, 12e-3, 4000)[:, None]),
                    ("held in the bone", None),
                )
                for phase, path in phases:
                    browser.execute_script("window.__dhgDraws = 0;")
                    f0, g0, r0, t0 = (
                        page.frames,
                        chromium_cpu_s("type=gpu"),
                        chromium_cpu_s("type=renderer"),
                        time.monotonic(),
                    )
                    if path is None:
                        time.sleep(hold_s)
                    else:
                        hand.move(path)
                        wait_for(hand.idle, 120, "the poses sent")
                    dt = time.monotonic() - t0
                    row = {
                        "variant": variant,
                        "phase": phase,
                        "gpu_cores": (chromium_cpu_s("type=gpu") - g0) / dt,
                        "renderer_cores": (chromium_cpu_s("type=renderer") - r0) / dt,
                        "draws_per_s": browser.execute_script("return window.__dhgDraws") / dt,
                        "page_updates_per_s": (page.frames - f0) / dt,
                    }
                    print(
                        f"{variant:8s} {phase:22s} gpu {row['gpu_cores']:.2f} renderer {row['renderer_cores']:.2f} "
                        f"cores, {row['draws_per_s']:.0f} draws/s, {row['page_updates_per_s']:.1f} drill updates/s",
                        flush=True,
                    )
                    rows.append(row)
            finally:
                hand.stop()
                viewer.close()
    finally:
        proc.stop()
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--hold", type=float, default=6.0, help="seconds each held phase is measured")
    args = ap.parse_args()
    rows: list[dict[str, Any]] = []
    for _ in range(args.rounds):
        rows += one_run("ours", args.hold)
        with viser_defaults():
            rows += one_run("viser", args.hold)
    print("\nmedians (Chromium cores: GPU process + renderer)")
    for phase in dict.fromkeys(r["phase"] for r in rows):
        med = {}
        for variant in ("ours", "viser"):
            sel = [
                r["gpu_cores"] + r["renderer_cores"] for r in rows if r["phase"] == phase and r["variant"] == variant
            ]
            med[variant] = statistics.median(sel)
        print(
            f"  {phase:22s} ours {med['ours']:.2f}  viser's defaults {med['viser']:.2f}"
            f"  ratio {med['ours'] / med['viser']:.2f}"
        )


if __name__ == "__main__":
    main()
