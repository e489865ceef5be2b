#!/usr/bin/env bash
# Builds the libFuzzer targets on stable Rust and runs each for SECONDS (default 20) from its
# committed seed corpus: `fuzz/run.sh [SECONDS]`. Coverage comes from rustc's -C flags (what
# cargo-fuzz passes), without a sanitizer, so no nightly toolchain is needed. New inputs found in
# a run go to a temporary folder (the committed corpus stays as it is); a crash leaves its input
# as crash-* in this folder and the script exits non-zero.
set -euo pipefail
cd "$(dirname "$0")"
each=${1:-20}
export CARGO_TARGET_DIR=${FUZZ_TARGET_DIR:-$PWD/target}
export RUSTFLAGS="--cfg fuzzing -Cpasses=sancov-module -Cllvm-args=-sanitizer-coverage-level=4 \
-Cllvm-args=-sanitizer-coverage-inline-8bit-counters -Cllvm-args=-sanitizer-coverage-pc-table \
-Cllvm-args=-sanitizer-coverage-trace-compares -Cdebug-assertions -Coverflow-checks"
# An explicit --target keeps RUSTFLAGS off the build scripts and proc macros (as cargo-fuzz does).
host=$(rustc -vV | sed -n 's/^host: //p')
cargo build --release --locked --bins -q --target "$host"
for target in decode_pose decode_prediction decode_ticks control; do
  found=$(mktemp -d)
  echo ">> fuzz $target for ${each} s"
  log="$found.log"
  status=0
  "$CARGO_TARGET_DIR/$host/release/$target" "$found" "corpus/$target" -max_total_time="$each" -timeout=5 \
    -rss_limit_mb=2048 -print_final_stats=1 > "$log" 2>&1 || status=$?
  grep -E "^stat::(number_of_executed_units|peak_rss_mb)|DONE|ERROR|panicked|SUMMARY" "$log" || true
  if [ "$status" -ne 0 ]; then tail -n 40 "$log"; fi
  rm -f "$log"
  rm -rf "$found"
  if [ "$status" -ne 0 ]; then echo "fuzz target $target failed (exit $status)"; exit 1; fi
done
