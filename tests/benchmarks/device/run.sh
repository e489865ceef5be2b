#!/usr/bin/env bash
# The issue-23/24 runs on a lent 16-core machine, with the kit pack.sh made (.devkit, carried):
# dhg-serve against the bare echo at 1, 4 and 16 clients (dhg, the engine alone, the echo,
# alternated), then the load with and without `dhg view` at 1 and 8 trainees. One call of the
# device tool, about 8 minutes with the defaults (26 runs of 10 s, each with its fresh server):
#
#   run(command="tests/benchmarks/device/run.sh", carry=[".devkit"], timeout_s=590)
#
# The JSON lines, each stage's log and machine.txt (the packages found, and whether the bundled
# model loads) land in $OUT (the device tool's folder; out/device elsewhere): 8 files at most, the
# device tool's limit. Each stage has a deadline, so a slow stage leaves the others' lines; a stage
# without time for two of its runs is skipped. Knobs (env):
#   STAGES        which runs, in order (default "server viewer viewer8"; also "smoke": 3 s of the
#                 engine against the echo at 2 clients, to check the kit; its lines in smoke.log)
#   RUN_SECONDS   seconds of load a run (default 10); ROUNDS (default 2); CLIENTS (default 1,4,16)
#   BUDGET        seconds for all stages (default 540, at most 560: one command of the device tool
#                 may run 600 s): a stage gets what is left at most
#   INSTALLED=1   PY already has dhg and its packages: the kit's wheels are not installed (to check
#                 the stages here, with .venv/bin/python)
#   DHG_SITE      where the wheels are installed (default /tmp/dhg-site)
#   MODEL_DEVICE  where the model's passes run, dhg-serve --device (default cpu: ONNX Runtime, as on
#                 the 2-core VM and a lab server without a GPU; auto picks the GPU)
set -euo pipefail
cd "$(dirname "$0")/../../.."
KIT=.devkit
OUT=${OUT:-out/device}
STAGES=${STAGES:-server viewer viewer8}
RUN_SECONDS=${RUN_SECONDS:-10}
ROUNDS=${ROUNDS:-2}
CLIENTS=${CLIENTS:-1,4,16}
MODEL_DEVICE=${MODEL_DEVICE:-cpu}
BUDGET=${BUDGET:-540}
[ "$BUDGET" -le 560 ] || { echo "run.sh: BUDGET $BUDGET is over 560 s (the device tool stops a command at 600)" >&2; exit 2; }
PY=${PY:-python3}
SITE=${DHG_SITE:-/tmp/dhg-site}
[ -d "$KIT/wheels" ] || { echo "run.sh: no $KIT here: run tests/benchmarks/device/pack.sh first and carry $KIT" >&2; exit 2; }
mkdir -p "$OUT"

if [ "${INSTALLED:-0}" != 1 ]; then
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" "$KIT"/wheels/*.whl
  export PYTHONPATH=$SITE${PYTHONPATH:+:$PYTHONPATH}
fi
export PYTHONUNBUFFERED=1 MODEL_DEVICE
BIN=$(mktemp -d)
trap 'rm -rf "$BIN"' EXIT
tar -xJf "$KIT/bin.tar.xz" -C "$BIN"

{
  echo "kit of commit $(tr "\n" " " < "$KIT/commit")run $(date -u +%FT%TZ)"
  echo "cores $(nproc); $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2- | sed 's/^ //'); kernel $(uname -r)"
  "$PY" - <<'PY'
import importlib
import importlib.metadata
import os
import platform

found = [f"python {platform.python_version()}"]
# What dhg imports that the kit carries, and what the machine's image must have.
for name, dist in (("dhg._bone_sim", "dhg"), ("zenoh", "eclipse-zenoh"), ("viser", "viser"),
                   ("msgspec", "msgspec"), ("websockets", "websockets"), ("trimesh", "trimesh"),
                   ("zstandard", "zstandard"), ("nibabel", "nibabel"), ("pydicom", "pydicom"),
                   ("numpy", "numpy"), ("onnxruntime", "onnxruntime"), ("torch", "torch")):
    try:
        m = importlib.import_module(name)
    except Exception as e:  # noqa: BLE001 - reported; the stage that needs it fails loudly
        found.append(f"{dist} MISSING ({type(e).__name__}: {e})")
        continue
    found.append(f"{dist} {importlib.metadata.version(dist)}")
    if name == "torch":
        found.append(f"cuda {m.cuda.is_available()}")
print(", ".join(found))
# The bundled model as dhg-serve loads it (the machine's torch is not the pinned one).
try:
    from dhg.learning.torchscript import load_model
    from dhg.learning.weights import default_model_path

    model = load_model(default_model_path(), device=os.environ.get("MODEL_DEVICE", "cpu"), executor="auto")
    print(f"bundled model loads: on {model.device}, passes by {model.executor}")
except Exception as e:  # noqa: BLE001 - reported: the server stages would fail the same way
    print(f"bundled model does NOT load: {type(e).__name__}: {e}")
PY
} | tee "$OUT/machine.txt"

# A stage may run until its deadline; what it printed and its lines stay.
stage() {
  local name=$1 limit=$2; shift 2
  local left=$(( BUDGET - SECONDS ))
  if [ "$left" -lt $(( 2 * per_run + 30 )) ]; then echo ">> $name: skipped, ${left} s of the budget left"; return; fi
  [ "$limit" -le "$left" ] || limit=$left
  echo ">> $name (at most ${limit} s): $*"
  local rc=0
  timeout --signal=INT --kill-after=20 "$limit" "$@" 2>&1 | tee "$OUT/$name.log" || rc=$?
  echo ">> $name: exit $rc"
}

per_run=$(( ${RUN_SECONDS%.*} + 8 ))
for s in $STAGES; do
  case $s in
    smoke)
      stage smoke 120 "$PY" tests/benchmarks/bench_server.py --against-echo --seconds 3 --clients 2 --rounds 1 \
        --variants dhg-engine,echo --load "$BIN/load" --echo "$BIN/echo" ;;
    server)
      n=$(( $(tr ',' '\n' <<<"$CLIENTS" | wc -l) * 3 * ROUNDS ))
      stage server $(( n * per_run + 60 )) "$PY" tests/benchmarks/bench_server.py --against-echo \
        --seconds "$RUN_SECONDS" --clients "$CLIENTS" --rounds "$ROUNDS" --variants dhg,dhg-engine,echo \
        --device "$MODEL_DEVICE" --load "$BIN/load" --echo "$BIN/echo" --out "$OUT/server.jsonl" ;;
    viewer)
      stage viewer $(( 2 * ROUNDS * (per_run + 6) + 60 )) "$PY" tests/benchmarks/bench_viewer.py \
        --seconds "$RUN_SECONDS" --rounds "$ROUNDS" --device "$MODEL_DEVICE" --load "$BIN/load" \
        --out "$OUT/viewer.jsonl" ;;
    viewer8)
      stage viewer8 $(( 2 * ROUNDS * (per_run + 8) + 60 )) "$PY" tests/benchmarks/bench_viewer.py \
        --seconds "$RUN_SECONDS" --rounds "$ROUNDS" --clients 8 --device "$MODEL_DEVICE" --load "$BIN/load" \
        --out "$OUT/viewer8.jsonl" ;;
    *) echo "run.sh: unknown stage $s (smoke, server, viewer, viewer8)" >&2; exit 2 ;;
  esac
done
