"""How many cortical breakthroughs does the session count per virtual-surgeon attempt? Every
attempt on the default phantom crosses the lateral cortex once, so a count of 0 is a missed
breakthrough and a count far above 1 means false ones. Runs the same subjects and attempts as
``dhg synth --seed SEED`` (4 experts and 4 novices × 3 attempts) and prints each attempt's count,
plunge (mm) and final distance to B (mm), then the spread per skill.

    python tests/benchmarks/breakthrough_counts.py [SEED ...]
"""

from __future__ import annotations

import sys
from collections import defaultdict

import numpy as np

from dhg import default_phantom
from dhg.core.session import DrillingSession
from dhg.operators.episodes import run_episode
from dhg.operators.styles import sample_style

BREAKTHROUGHS = 8  # index in the session's feedback tuple


def main() -> None:
    seeds = [int(s) for s in sys.argv[1:]] or [0]
    phantom = default_phantom()
    session = DrillingSession(phantom.volume, phantom.path)
    counts: dict[str, list[int]] = defaultdict(list)
    for seed in seeds:
        for skill in ("expert", "novice"):
            k = 0 if skill == "expert" else 1
            for index in range(4):
                style = sample_style(skill, np.random.default_rng([seed, k, index]))
                for attempt in range(3):
                    rng = np.random.default_rng([seed, k, index, attempt + 1])
                    ep = run_episode(session, style, rng, f"{skill[0]}{index}", attempt)
                    n = int(session._s.feedback()[BREAKTHROUGHS])
                    counts[skill].append(n)
                    m = ep.metrics
                    print(
                        f"seed {seed} {skill} {index} attempt {attempt}: {n} breakthrough(s), "
                        f"plunge {m['plunge_depth_m'] * 1e3:.2f} mm, to B {m['target_distance_m'] * 1e3:.1f} mm",
                        flush=True,
                    )
    for skill, ns in counts.items():
        hist = {v: ns.count(v) for v in sorted(set(ns))}
        print(f"{skill}: {len(ns)} attempts, breakthroughs per attempt {hist}")


if __name__ == "__main__":
    main()
