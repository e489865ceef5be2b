#!/usr/bin/env bash
# Packs what the issue-23/24 runs need on a lent 16-core machine into .devkit/ (git-ignored): the
# extension as a CPython 3.12 wheel (the machine's python3 is 3.12, with torch, onnxruntime, numpy
# and the rest; nothing can be fetched there), the Python packages it lacks as wheels, and the load
# tool and the echo, stripped. Run here, then carry .devkit to the machine and run run.sh there
# (docs/development.md, "Runs on a lent 16-core machine").
#
#   make device-kit            # or: tests/benchmarks/device/pack.sh
#
# PY312 names a CPython 3.12 to build the wheel against (default: python3.12 on PATH, else pyenv's).
set -euo pipefail
cd "$(dirname "$0")/../../.."
KIT=.devkit
DEPS_PY=${DEPS_PY:-.venv/bin/python}
MATURIN=${MATURIN:-.venv/bin/maturin}
: "${CARGO_TARGET_DIR:=$HOME/.cache/dhg/target}"
export CARGO_TARGET_DIR
is312() { "$1" -c 'import sys; assert sys.version_info[:2] == (3, 12)' 2>/dev/null; }
if [ -z "${PY312:-}" ]; then
  for c in python3.12 "$HOME"/.pyenv/versions/3.12*/bin/python3.12; do
    if is312 "$c"; then PY312=$c; break; fi
  done
fi
if [ -z "${PY312:-}" ] || ! is312 "$PY312"; then
  echo "pack.sh: no CPython 3.12 found (set PY312=/path/to/python3.12)" >&2
  exit 2
fi
# The packages of requirements.lock that the machine's image lacks (KINDS.md of the device tool),
# at the lock's versions. run.sh imports each of them there, and loads the bundled model.
MISSING="eclipse-zenoh msgspec nibabel pydicom trimesh viser websockets zstandard"

rm -rf "$KIT" && mkdir -p "$KIT/wheels"
echo ">> the extension for CPython 3.12 ($PY312)"
PIP_QUIET=1 "$MATURIN" build --release --strip -q -i "$PY312" --out "$KIT/wheels"
echo ">> the load tool and the echo"
cargo build --release -q -p bone_sim --example load --example echo
# Stripped and compressed (about 7 MiB for both): run.sh unpacks them.
bins=$(mktemp -d)
for b in load echo; do strip -o "$bins/$b" "$CARGO_TARGET_DIR/release/examples/$b"; done
tar -cJf "$KIT/bin.tar.xz" -C "$bins" load echo && rm -rf "$bins"
echo ">> wheels the machine lacks: $MISSING"
for name in $MISSING; do
  pin=$(grep -i -E "^${name//-/[-_]}==" requirements.lock) || { echo "pack.sh: $name is not in requirements.lock" >&2; exit 2; }
  "$DEPS_PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    --platform manylinux_2_5_x86_64 --platform manylinux1_x86_64 -d "$KIT/wheels" "$pin"
done
{ git rev-parse HEAD; git diff --quiet HEAD -- . || echo "with uncommitted changes"; } > "$KIT/commit"
size=$(( $(du -sb "$KIT" | cut -f1) / 1048576 ))
echo ">> $KIT: ${size} MiB (the device tool carries 64 MiB with the working tree)"
ls -1 "$KIT/wheels"
if [ "$size" -ge 45 ]; then echo "pack.sh: $KIT is over 44 MiB (the tree itself is about 15)" >&2; exit 1; fi
