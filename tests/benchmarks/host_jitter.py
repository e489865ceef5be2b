"""How late does this machine wake a thread that sleeps to 1 ms deadlines? The floor under the
engine's tick lateness: a 1 kHz loop of ``time.sleep`` to absolute deadlines for 10 s, with
SCHED_FIFO when allowed (as the engine's tick thread asks for), printing the lateness quantiles
and the wake-ups a whole period late (what the engine counts as missed ticks).

    python tests/benchmarks/host_jitter.py [SECONDS]
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np


def main() -> None:
    seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 10.0
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(80))
        rt = "SCHED_FIFO 80"
    except (PermissionError, AttributeError, OSError):
        rt = "normal scheduling"
    n = int(seconds * 1000)
    late = np.empty(n)
    t0 = time.monotonic_ns()
    for k in range(n):
        deadline = t0 + (k + 1) * 1_000_000
        pause = deadline - time.monotonic_ns()
        if pause > 0:
            time.sleep(pause * 1e-9)
        late[k] = time.monotonic_ns() - deadline
    ms = late / 1e6
    print(
        f"{rt}, {n} deadlines: lateness p50 {np.percentile(ms, 50):.3f} ms, p99 {np.percentile(ms, 99):.3f} ms, "
        f"p99.9 {np.percentile(ms, 99.9):.3f} ms, max {ms.max():.2f} ms; {int((ms >= 1.0).sum())} wake-ups ≥ 1 ms late"
    )


if __name__ == "__main__":
    main()
