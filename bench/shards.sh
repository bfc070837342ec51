#!/usr/bin/env bash
# Shard benchmark: a diffuse Cornell box (walls as separate quads, two diffuse blocks: the
# form factors dominate, as in the rooms users make) at 50,000 patches (default), on one box and as
# K = 2 and K = 4 shards plus a merge, through the real translux-precompute binary, as a
# 2-CPU scheduler node runs them (two single-threaded shards at a time). Prints a markdown
# table — per-shard times, the merge's cost and share, and F's wall time with two shards
# against one single-threaded task — and appends it, with the date and machine, to
# bench/results/shards-DATE.md. It also checks that each merged bundle's arrays are the
# one-box bundle's bytes. Not a test: nothing here asserts a time. `--scene SCENE` takes
# another scene (e.g. builtin:bowls, where the shards' subsurface cuts count too); BIN=PATH
# times that translux-precompute binary instead of building one (an older build, say).
#
#   bash bench/shards.sh [PATCHES] [--profile PROFILE] [--scene SCENE]
#                                                          (default: 50000, release)
set -euo pipefail
cd "$(dirname "$0")/.."
patches=50000
profile=release
scene=
while [ $# -gt 0 ]; do
  case "$1" in
    --profile) profile="$2"; shift 2 ;;
    --scene) scene="$2"; shift 2 ;;
    *) patches="$1"; shift ;;
  esac
done
if [ -n "${BIN:-}" ]; then
  bin="$BIN"
else
  cargo build -q --profile "$profile" -p translux-precompute
  dir=$([ "$profile" = dev ] || [ "$profile" = test ] && echo debug || echo "$profile")
  bin="target/$dir/translux-precompute"
fi
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
described="a diffuse Cornell box of separate quads and boxes (bench/shards.sh)"
if [ -n "$scene" ]; then
  described="$scene"
else
scene="$work/cornell-diffuse.json"
cat > "$scene" <<'JSON'
{"unit_mm": 100,
 "objects": [
  {"name": "floor", "mesh": {"shape": "quad", "size": [5.55, 5.55]},
   "material": {"type": "diffuse", "albedo": [0.73, 0.73, 0.73]}},
  {"name": "ceiling", "mesh": {"shape": "quad", "size": [5.55, 5.55]},
   "transform": {"rotate_deg": [180, 0, 0], "translate": [0, 5.55, 0]},
   "material": {"type": "diffuse", "albedo": [0.73, 0.73, 0.73]}},
  {"name": "back", "mesh": {"shape": "quad", "size": [5.55, 5.55]},
   "transform": {"rotate_deg": [90, 0, 0], "translate": [0, 2.775, -2.775]},
   "material": {"type": "diffuse", "albedo": [0.73, 0.73, 0.73]}},
  {"name": "left", "mesh": {"shape": "quad", "size": [5.55, 5.55]},
   "transform": {"rotate_deg": [0, 0, -90], "translate": [-2.775, 2.775, 0]},
   "material": {"type": "diffuse", "albedo": [0.63, 0.06, 0.05]}},
  {"name": "right", "mesh": {"shape": "quad", "size": [5.55, 5.55]},
   "transform": {"rotate_deg": [0, 0, 90], "translate": [2.775, 2.775, 0]},
   "material": {"type": "diffuse", "albedo": [0.14, 0.45, 0.09]}},
  {"name": "short_block", "mesh": {"shape": "box", "size": [1.65, 1.65, 1.65]},
   "transform": {"rotate_deg": [0, -17, 0], "translate": [0.9, 0.825, 0.7]},
   "material": {"type": "diffuse", "albedo": [0.73, 0.73, 0.73]}},
  {"name": "tall_block", "mesh": {"shape": "box", "size": [1.65, 3.3, 1.65]},
   "transform": {"rotate_deg": [0, 20, 0], "translate": [-0.9, 1.65, -0.8]},
   "material": {"type": "diffuse", "albedo": [0.73, 0.73, 0.73]}}
 ],
 "lights": [{"type": "point", "position": [0, 5.3, 0], "intensity": [40, 40, 40]}]}
JSON
fi

now() { date +%s.%N; }
secs() { awk -v a="$1" -v b="$2" 'BEGIN { printf "%.1f", b - a }'; }
stage() { # SUMMARY NAME -> seconds of that stage line
  printf '%s\n' "$1" | grep -E "^ +(stage times +)?$2 [0-9.]+ s" | head -n1 | awk '{print $(NF-1)}'
}

# One box: every core, and one thread (the single task two shards are set against).
t0=$(now)
one=$("$bin" "$scene" --out "$work/one" --patches "$patches" -q)
one_wall=$(secs "$t0" "$(now)")
one_f=$(stage "$one" "form factors")
one_env=$(stage "$one" "environment")
t0=$(now)
single=$("$bin" "$scene" --out "$work/single" --patches "$patches" -q --threads 1)
single_f=$(stage "$single" "form factors")
single_env=$(stage "$single" "environment")
rm -rf "$work/single"

rows=()
for k in 2 4; do
  out="$work/k$k"
  shard_times=()
  t0=$(now)
  for ((i = 0; i < k; i += 2)); do
    pids=()
    for j in $i $((i + 1)); do
      [ "$j" -lt "$k" ] || continue
      "$bin" "$scene" --out "$out" --patches "$patches" -q --threads 1 --shard "$j/$k" \
        > "$work/shard-$k-$j.txt" &
      pids+=($!)
    done
    for p in "${pids[@]}"; do wait "$p"; done
  done
  shards_wall=$(secs "$t0" "$(now)")
  for ((j = 0; j < k; j++)); do
    line=$(grep 'stage times' "$work/shard-$k-$j.txt")
    f=$(printf '%s' "$line" | sed -E 's/.*form factors ([0-9.]+) s.*/\1/')
    e=$(printf '%s' "$line" | sed -E 's/.*environment ([0-9.]+) s.*/\1/')
    c=0
    if printf '%s' "$line" | grep -q 'subsurface cuts'; then
      c=$(printf '%s' "$line" | sed -E 's/.*subsurface cuts ([0-9.]+) s.*/\1/')
    fi
    shard_times+=("$(awk -v f="$f" -v e="$e" -v c="$c" 'BEGIN { printf "%.1f", f + e + c }')")
  done
  t0=$(now)
  merged=$("$bin" "$scene" --out "$out" --patches "$patches" -q --merge "$k")
  merge_wall=$(secs "$t0" "$(now)")
  parts=$(stage "$merged" "merge parts")
  total=$(awk -v a="$shards_wall" -v b="$merge_wall" 'BEGIN { printf "%.1f", a + b }')
  share=$(awk -v m="$merge_wall" -v t="$total" 'BEGIN { printf "%.0f%%", 100 * m / t }')
  same=yes
  for f in "$work/one"/*; do
    name=$(basename "$f")
    [ "$name" = manifest.json ] && continue
    cmp -s "$f" "$out/$name" || same="NO ($name differs)"
  done
  joined=$(printf ' / %s' "${shard_times[@]}")
  rows+=("| $k | ${joined:3} | $shards_wall | $merge_wall ($parts reading parts) | $share | $total | $same |")
  rm -rf "$out"
done

patch_count=$(printf '%s\n' "$one" | grep -m1 '^  patches ' | awk '{print $2}')
cpu=$(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ *//')
table=$(
  echo "$described, $patch_count patches, $(nproc) cores ($cpu), profile $profile, $(date -u +%F)"
  echo
  echo "One box, every core: $one_wall s wall (form factors $one_f s, environment $one_env s)."
  echo "One task, one thread: form factors $single_f s, environment $single_env s."
  echo
  echo "| K | each shard: F + environment + S cuts (s) | shards, two at a time, wall (s) | merge wall (s) | merge share | total (s) | arrays = one box |"
  echo "|---|---|---|---|---|---|---|"
  printf '%s\n' "${rows[@]}"
)
echo "$table"
mkdir -p bench/results
printf '%s\n\n' "$table" >> "bench/results/shards-$(date -u +%F).md"
