#!/usr/bin/env bash
# Links per patch at growing N: the hierarchical F's one-sided cut (receiver patches to
# source clusters, the default) against the two-sided one (`--links two-sided`: clusters
# receive too), on one scene at the default accuracy, through the real translux-precompute
# binary. Prints a markdown table — entries of C per patch (to nodes and to patches), F̃'s
# bytes, the largest row sum, rays and the F stage's time — and appends it, with the date
# and machine, to bench/results/links-DATE.md. Not a test: nothing here asserts a time.
#
#   bash bench/links.sh [SCENE] [--sizes "6000 25000 100000"] [--profile PROFILE]
#   (defaults: builtin:cornell, 6000 25000, release)
set -euo pipefail
cd "$(dirname "$0")/.."
scene=builtin:cornell
sizes="6000 25000"
profile=release
while [ $# -gt 0 ]; do
  case "$1" in
    --profile) profile="$2"; shift 2 ;;
    --sizes) sizes="$2"; shift 2 ;;
    *) scene="$1"; shift ;;
  esac
done
cargo build -q --profile "$profile" -p translux-precompute
dir=$([ "$profile" = dev ] || [ "$profile" = test ] && echo debug || echo "$profile")
bin="target/$dir/translux-precompute"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

table=$(
  echo "| links | patches | entries per patch | to nodes | to patches | F̃ (MiB) | largest row sum | rays | F stage (s) |"
  echo "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"
  for n in $sizes; do
    for links in one-sided two-sided; do
      out="$work/$links-$n"
      summary=$("$bin" "$scene" --patches "$n" --links "$links" --env-bins 0 --out "$out" 2>&1)
      ff=$(printf '%s\n' "$summary" | grep -E '^ +(stage times +)?form factors [0-9.]+ s' | head -n1 | awk '{print $(NF-1)}')
      python3 - "$out/manifest.json" "$links" "$ff" <<'PY'
import json, sys
m = json.load(open(sys.argv[1]))
n, f, h = m["patch_count"], m["form_factors"], m["hierarchy"]
print(f"| {sys.argv[2]} | {n:,} | {f['nnz'] / n:.0f} | {h['node_entries'] / n:.0f} | "
      f"{h['patch_entries'] / n:.0f} | {f['nnz'] * 8 / 2**20:.1f} | {f['row_sum_max']:.4f} | "
      f"{f['rays'] / 1e6:.0f} M | {sys.argv[3]} |")
PY
      rm -rf "$out"
    done
  done
)
printf '%s\n' "$table"
mkdir -p bench/results
{
  echo "## $(date -u +%Y-%m-%d) $scene, $(nproc) CPUs ($(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs)), --profile $profile"
  echo
  printf '%s\n\n' "$table"
} >> "bench/results/links-$(date -u +%Y-%m-%d).md"
