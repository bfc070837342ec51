#!/bin/bash
# The GPU figures of docs/gpu.md on a machine with a GPU, in one run:
#   bench/scripts/device_check.sh BIN_DIR DATA_DIR OUT_DIR
# BIN_DIR holds release builds of `table1` (translux-tests) and `gpu_bench` (translux-server):
#   cargo build --release -p translux-tests --example table1 -p translux-server --example gpu_bench
# DATA_DIR is ../shared/data (the bowls scene reads the bunny from /work/shared/data, where
# this script links it). Writes gpu_bench.md, table1-gpu.log, table1-cpu.log and tables.md.
set -u
BIN=$1; DATA=$2; OUT=$3
mkdir -p "$OUT" /work/shared /tmp/device-keep /tmp/device-tables
[ -e /work/shared/data ] || ln -s "$(realpath "$DATA")" /work/shared/data
export WGPU_BACKEND=vulkan RUST_LOG=translux_server=info
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader > "$OUT/device.txt" 2>&1
echo "== gpu_bench (Cornell box, 24,640 patches, no T)"
timeout 200 "$BIN/gpu_bench" --patches 24640 --no-t --reps 5 > "$OUT/gpu_bench.md" 2> "$OUT/gpu_bench.err"
echo "rc $?"; grep -E "^\| |^### |^GPU bytes" "$OUT/gpu_bench.md"
table1() {
  name=$1; shift
  echo "== $name"
  timeout 200 "$BIN/table1" "$@" --no-mitsuba --keep /tmp/device-keep --out "/tmp/device-tables/$name" \
    > "$OUT/$name.log" 2>&1
  echo "rc $?"; grep -E "^\| (Cornell|Bowls) .*(gpu|cpu) \|$" "$OUT/$name.log" | head -8
}
table1 table1-gpu --scenes cornell,bowls --backend gpu --reps 12
table1 table1-cpu --scenes cornell --backend cpu --reps 12
for d in /tmp/device-tables/*; do echo "### $d"; cat "$d"/*.md; done > "$OUT/tables.md"
