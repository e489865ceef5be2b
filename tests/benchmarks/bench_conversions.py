"""Two conversions that run once per message or per write, alternated in one run:

- a dataset's records table (``dhg.data.dataset._records_table``, Arrow arrays from numpy) against
  the per-value Python lists it replaced (``pa.Table.from_pydict`` of ``.tolist()`` columns), on an
  hour of 10 Hz records (10 attempts of 3,600), the size a long ``dhg record`` rewrites per flush;
- ``DrillingSession.state()`` (the core's ``SessionState`` through serde + pythonize).

Usage: python tests/benchmarks/bench_conversions.py      (prints a Markdown table)
"""

from __future__ import annotations

import statistics
import time

import numpy as np
import pyarrow as pa

import dhg
from dhg.core.features import FEATURE_NAMES
from dhg.core.session import DrillingSession
from dhg.data.dataset import EpisodeInput, _records_table, records_schema


def _lists_table(episodes: list[EpisodeInput]) -> pa.Table:
    """The records table as it was built before: one Python list per column, value by value."""
    cols: dict[str, list] = {name: [] for name in records_schema().names}
    for eid, ep in enumerate(episodes):
        r, m = ep.records, len(ep.records)
        cols["episode_id"] += [eid] * m
        cols["subject_id"] += [ep.subject_id] * m
        cols["skill"] += [ep.skill] * m
        cols["attempt"] += [int(ep.attempt)] * m
        cols["time_s"] += r[:, 0].tolist()
        for i, name in enumerate(FEATURE_NAMES):
            cols[name] += (r[:, 1 + i].astype(np.int8) if name == "layer" else r[:, 1 + i]).tolist()
        cols["drill_on"] += (r[:, 10] > 0.5).tolist()
    return pa.Table.from_pydict(cols, schema=records_schema())


def _median_ms(f, arg, repeats: int = 5) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        f(arg)
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def main() -> None:
    rng = np.random.default_rng(0)
    episodes = []
    for attempt in range(10):
        r = np.c_[rng.random((3600, 10)), np.ones(3600)]
        r[:, 8] = 1.0  # the layer column: an id
        episodes.append(EpisodeInput("s0", "expert", attempt, r))
    assert _records_table(episodes).equals(_lists_table(episodes)), "the two builds differ"
    rounds = {"numpy": [], "lists": []}
    for _ in range(3):  # alternating, so drift on a shared machine hits both alike
        rounds["numpy"].append(_median_ms(_records_table, episodes))
        rounds["lists"].append(_median_ms(_lists_table, episodes))
    p = dhg.default_phantom()
    native = DrillingSession(p.volume, p.path)._s
    n = 20_000
    t0 = time.perf_counter()
    for _ in range(n):
        native.state()
    state_us = (time.perf_counter() - t0) / n * 1e6
    print("| workload | figure |")
    print("|---|---|")
    for name, ms in rounds.items():
        print(f"| records table, 36,000 rows, {name} | {' / '.join(f'{v:.1f}' for v in ms)} ms (3 rounds) |")
    ratio = statistics.median(rounds["lists"]) / statistics.median(rounds["numpy"])
    print(f"| lists / numpy | {ratio:.1f}x |")
    print(f"| DrillingSession.state() | {state_us:.2f} us per call ({n} calls) |")


if __name__ == "__main__":
    main()
