"""What the model predicts at the start of an attempt that follows a reset (decision 0036):
``dhg-serve`` on the 1 mm phantom with the bundled model, one trainee drilling 4 s into the
cortex, a ``reset``, then the stylus held 3 mm before the entry point for 3 s. Prints the norm of
the predicted expert force (N) of each of the new attempt's first 20 model replies, and of the
last 5. Since 0036 the new attempt's windows hold its own records only, so the first 20 are as
steady as the last; before, they began with the end of the attempt before.

    python tests/benchmarks/reset_guidance.py
    PYTHONPATH=/tmp/old/python python tests/benchmarks/reset_guidance.py   # another build

(For another build: ``maturin build --release -o DIR`` in a worktree of it, then unzip
``dhg/_bone_sim*.so`` from the wheel into a ``git archive`` copy of its ``python/``.)
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dhg.live.client import TraineeClient  # noqa: E402
from support import Stylus, entry, serve, wait_until  # noqa: E402


def main() -> None:
    proc, endpoint = serve("--idle-timeout", "600")
    try:
        with TraineeClient(endpoint, "reset-guidance") as c:
            a, d, q = entry(c)
            stylus = Stylus(c, q)
            stylus.move(a + d * np.linspace(-3e-3, 5e-3, 4000)[:, None])
            wait_until(lambda: stylus.idle() and len(c.guidance) >= 30, 60, "the first attempt drilled")
            held = len(c.guidance)  # the workload: five replies more (0.5 s) with the stylus held in the bone
            wait_until(lambda: len(c.guidance) >= held + 5, 60, "the stylus held in the bone")
            n = len(c.guidance)
            c.control("reset")
            stylus.move(np.repeat((a - 3e-3 * d)[None, :], 3000, axis=0))
            wait_until(stylus.idle, 60, "3 s before the entry point")
            last = len(c.guidance)  # the replies to the last windows: three more, the stylus held
            wait_until(lambda: len(c.guidance) >= last + 3, 60, "the replies to the last windows")
            after = list(c.guidance)[n:]
            stylus.stop()
    finally:
        proc.stop()
    norms = np.linalg.norm(np.array([g["predicted_force_n"] for g in after]), axis=1)
    print(
        json.dumps(
            {
                "replies": len(after),
                "first_20_n": np.round(norms[:20], 3).tolist(),
                "last_5_n": np.round(norms[-5:], 3).tolist(),
            }
        )
    )


if __name__ == "__main__":
    main()
