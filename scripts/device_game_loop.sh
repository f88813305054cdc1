#!/usr/bin/env bash
# Issue 37's goal figures on a machine with a real GPU (the `device` tool, when a session is lent
# one): `game_loop --json --stage-ms` at 1920x1080 on the column scene and on the double dam break
# resampled to 100,000 particles, GPU milliseconds per stage and pass from timestamp queries,
# CPU milliseconds of `prepare`, each saved frame against the CPU pipeline. Lavapipe proves
# correctness only; run this where the GPU is real.
#
# The other machine builds nothing: build here, strip (the carried tree is limited to 64 MiB)
# and carry the binary with the data file, in a folder git ignores:
#   cargo build --release --example game_loop
#   mkdir -p .device && grep -qx '/.device/' .git/info/exclude || echo /.device/ >> .git/info/exclude
#   strip -o .device/game_loop target/release/examples/game_loop
#   cp tests/data/double_dam_break_frame_26_4732_particles.vtk .device/
# then run there (carry [".device"]): scripts/device_game_loop.sh .device "$OUT"
#
# Sizes and frames can be lowered to try it here on lavapipe: SIZE=64x48 FRAMES=3 PARTICLES=20000.
set -euo pipefail
dir=${1:-.device}
out=${2:-${OUT:-out/device}}
size=${SIZE:-1920x1080}
frames=${FRAMES:-30}
particles=${PARTICLES:-100000}
mkdir -p "$out"
if ! ldconfig -p 2>/dev/null | grep -q libvulkan; then
  echo "warning: no Vulkan loader (libvulkan) here: see the device tool's README for carrying one" >&2
fi
if [ -z "${VK_DRIVER_FILES:-}" ] && [ -f /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json ]; then
  export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
fi
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | tee "$out/gpu.txt" || true
run() {
  local name=$1
  shift
  echo "== $name" >&2
  # (the JSON report is the last line; the saved frames go beside it)
  timeout 240 "$dir/game_loop" --frames "$frames" --size "$size" --stage-ms --json \
    --save "$((frames - 1))" --out "$out/$name" "$@" | tail -n 1 | tee "$out/$name.json"
}
run column
run column_moving --renderer ssfr --orbit 1
run ddb_${particles} --input "$dir/double_dam_break_frame_26_4732_particles.vtk" --particles "$particles"
