#!/usr/bin/env bash
# Foundation benchmark: builtin:cornell_paper at 6,000 and 24,640 patches through the real
# translux-precompute binary. Prints a markdown table (form-factor time, occlusion rays/s,
# nnz(F), bundle bytes, peak RSS) and appends it, with the date and machine, to
# bench/results/foundation-DATE.md. Not a test: nothing here asserts a time.
#
#   bash bench/foundation.sh [PATCHES ...]      (default: 6000 24640)
set -euo pipefail
cd "$(dirname "$0")/.."
sizes=("$@")
[ ${#sizes[@]} -gt 0 ] || sizes=(6000 24640)

cargo build --release -q -p translux-precompute
bin=target/release/translux-precompute
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

cpu=$(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ *//')
header="| requested | patches | F time (s) | rays | M rays/s | nnz(F) | nnz/N² | bundle (MiB) | peak RSS (GiB) | total (s) |"
rule="|---|---|---|---|---|---|---|---|---|---|"
rows=()
for n in "${sizes[@]}"; do
  start=$(date +%s.%N)
  summary=$("$bin" builtin:cornell_paper --out "$work/cornell-$n" --patches "$n" -q)
  end=$(date +%s.%N)
  get() { printf '%s\n' "$summary" | grep -m1 "$1" ; }
  patches=$(get '^  patches ' | awk '{print $2}')
  nnz=$(get 'nnz(F)' | awk '{print $2}')
  rays=$(get 'occlusion rays' | awk '{print $3}')
  mrays=$(get 'occlusion rays' | sed -E 's/.*\(([0-9.]+) M rays.*/\1/')
  ff=$(printf '%s\n' "$summary" | grep -m1 'form factors' | awk '{print $(NF-1)}')
  bytes=$(get '^  bundle ' | sed -E 's/.*\(([0-9]+) bytes\).*/\1/')
  rss=$(get 'peak memory' | awk '{print $(NF-1), $NF}')
  density=$(awk -v z="$nnz" -v p="$patches" 'BEGIN{printf "%.1f%%", 100*z/(p*p)}')
  mib=$(awk -v b="$bytes" 'BEGIN{printf "%.1f", b/1048576}')
  total=$(awk -v a="$start" -v b="$end" 'BEGIN{printf "%.1f", b-a}')
  rows+=("| $n | $patches | $ff | $rays | $mrays | $nnz | $density | $mib | $rss | $total |")
  rm -rf "$work/cornell-$n"
done

report=$(
  echo "## builtin:cornell_paper form factors — $(date -u +%Y-%m-%d), $(nproc) cores, $cpu"
  echo
  echo "$header"
  echo "$rule"
  printf '%s\n' "${rows[@]}"
  echo
  echo "Paper (Sheng et al. 2013, Table 1): 24,640 polygons, F+S precompute 4 min + 3 min on a quad-core i7 + GTX 590."
)
printf '%s\n' "$report"
out="bench/results/foundation-$(date -u +%Y-%m-%d).md"
printf '%s\n\n' "$report" >> "$out"
echo "saved to $out" >&2
