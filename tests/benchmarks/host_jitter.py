"""How late does this machine wake a thread that sleeps to 1 ms deadlines? The floor under the
engine's tick lateness: a 1 kHz loop of ``time.sleep`` to absolute deadlines for 10 s, with
SCHED_FIFO when allowed (as the engine's tick thread asks for), printing the lateness quantiles
and the wake-ups a whole period late (what the engine counts as missed ticks). With ``--spin`` it
busy-waits to each deadline instead (as ``dhg-serve --wait spin`` does): what is left is the
host taking the core away.

    python tests/benchmarks/host_jitter.py [SECONDS] [--spin]
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np


def main() -> None:
    args = [a for a in sys.argv[1:] if a != "--spin"]
    spin = len(args) < len(sys.argv) - 1
    seconds = float(args[0]) if args else 10.0
    rt = "normal scheduling"
    try:
        # Not when spinning: the kernel's real-time throttling (sched_rt_runtime_us, 95 % by
        # default) would stop a spinning SCHED_FIFO thread for 50 ms every second.
        if not spin:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(80))
            rt = "SCHED_FIFO 80"
    except (PermissionError, AttributeError, OSError):
        pass
    n = int(seconds * 1000)
    late = np.empty(n)
    t0 = time.monotonic_ns()
    for k in range(n):
        deadline = t0 + (k + 1) * 1_000_000
        pause = deadline - time.monotonic_ns()
        if spin:
            while time.monotonic_ns() < deadline:
                pass
        elif pause > 0:
            time.sleep(pause * 1e-9)
        late[k] = time.monotonic_ns() - deadline
    ms = late / 1e6
    print(
        f"{rt}, {'spin' if spin else 'sleep'}, {n} deadlines: lateness"
        f" p50 {np.percentile(ms, 50):.3f} ms, p99 {np.percentile(ms, 99):.3f} ms, "
        f"p99.9 {np.percentile(ms, 99.9):.3f} ms, max {ms.max():.2f} ms; {int((ms >= 1.0).sum())} wake-ups ≥ 1 ms late"
    )


if __name__ == "__main__":
    main()
