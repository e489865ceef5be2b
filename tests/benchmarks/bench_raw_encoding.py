"""How the 1 kHz stream's Parquet encodings compare (decision 0037): a raw file (``raw.parquet`` or
a part of a recording) rewritten in memory with pyarrow's defaults and as DHG writes it
(:func:`dhg.data.dataset.raw_parquet_options`), and two variants not chosen (zstd alone; DHG's
encodings with zstd at level 9), alternated; per column the bytes a row each way and
how often its value changes from one tick to the next; per way the bytes a row, and the write and
read times (medians). Checks that both read back equal to the input.

    python tests/benchmarks/bench_raw_encoding.py DATASET/raw.parquet [--rounds 5] [--out FILE]

A recording to try it on: ``dhg record --raw`` (or ``tests/benchmarks/bench_record.py``, whose
folder is removed at its end), or ``dhg synth --raw`` (virtual surgeons drill without guidance, so
their guidance columns are all zeros).
"""

from __future__ import annotations

import argparse
import io
import json
import statistics
import time
from typing import Any

import numpy as np
import pyarrow.parquet as pq

from dhg.data.dataset import raw_parquet_options


def _write(table: Any, options: dict[str, Any]) -> tuple[bytes, float]:
    buf = io.BytesIO()
    t0 = time.perf_counter()
    pq.write_table(table, buf, **options)
    return buf.getvalue(), time.perf_counter() - t0


def _column_bytes(data: bytes) -> dict[str, int]:
    md = pq.ParquetFile(io.BytesIO(data)).metadata
    out: dict[str, int] = {}
    for g in range(md.num_row_groups):
        for c in range(md.num_columns):
            col = md.row_group(g).column(c)
            out[col.path_in_schema] = out.get(col.path_in_schema, 0) + col.total_compressed_size
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("raw", help="a Parquet file of the 1 kHz stream")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--out", help="also append the JSON line to this file")
    args = ap.parse_args()
    table = pq.read_table(args.raw)
    rows = table.num_rows
    dhg = raw_parquet_options(table.schema)
    # pyarrow's defaults; zstd alone; DHG's; DHG's with zstd at level 9 (the two not chosen).
    ways = {"defaults": {}, "zstd": {"compression": "zstd"}, "dhg": dhg, "dhg-zstd9": {**dhg, "compression_level": 9}}
    times: dict[str, dict[str, list[float]]] = {w: {"write": [], "read": []} for w in ways}
    data: dict[str, bytes] = {}
    for _ in range(args.rounds):
        for way, options in ways.items():
            data[way], dt = _write(table, options)
            times[way]["write"].append(dt)
            t0 = time.perf_counter()
            back = pq.read_table(io.BytesIO(data[way]))
            times[way]["read"].append(time.perf_counter() - t0)
            if not back.equals(table):
                raise SystemExit(f"{way}: the table did not read back equal")
    per_column = {w: _column_bytes(d) for w, d in data.items()}
    result = {
        "file": args.raw,
        "rows": rows,
        "rounds": args.rounds,
        "bytes_per_row": {w: round(len(d) / rows, 2) for w, d in data.items()},
        "write_ms": {w: round(statistics.median(t["write"]) * 1e3, 2) for w, t in times.items()},
        "read_ms": {w: round(statistics.median(t["read"]) * 1e3, 2) for w, t in times.items()},
        "columns": {
            name: {
                **{w: round(per_column[w][name] / rows, 2) for w in ways},
                "changes": int(np.count_nonzero(np.diff(table.column(name).to_numpy()))),
            }
            for name in table.column_names
        },
    }
    print(f"{rows} rows, {args.rounds} rounds alternated; medians\n")
    print("| | bytes a row | write (ms) | read (ms) |\n|---|---:|---:|---:|")
    for w in ways:
        print(f"| {w} | {result['bytes_per_row'][w]} | {result['write_ms'][w]} | {result['read_ms'][w]} |")
    print("\n| column | " + " | ".join(f"{w} (bytes a row)" for w in ways) + " | value changes |")
    print("|---|" + "---:|" * (len(ways) + 1))
    for name, c in result["columns"].items():
        print(f"| {name} | " + " | ".join(str(c[w]) for w in ways) + f" | {c['changes']} |")
    if args.out:
        with open(args.out, "a") as fh:
            fh.write(json.dumps(result) + "\n")


if __name__ == "__main__":
    main()
