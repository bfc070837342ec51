#!/bin/bash
# Device check 3: the GPU backend as it starts (S made on the CPU), Table 1's rows.
for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig
mkdir -p /work/shared && cp -r .dev/data /work/shared/data
B=.dev/bin/table1; K=/tmp/keep; mkdir -p $K
export RUST_LOG=translux_server=info,translux_engine=info
run() { name=$1; shift; echo "== $name"; timeout 200 "$@" --no-mitsuba --keep $K --out /tmp/r/$name > $OUT/$name.log 2>&1; echo "rc $?"; grep -E "^\| (Cornell|Bowls) .*(gpu|cpu) \|$" $OUT/$name.log | head -8; grep -o "translucency change: medians[^;]*;[^;]*;" $OUT/$name.log; }
run gpu $B --scenes cornell,bowls --backend gpu --reps 12
RAYON_NUM_THREADS=2 run gpu2threads taskset -c 0,1 $B --scenes bowls --backend gpu --reps 12
run full $B --scenes bowls --full --backend gpu --reps 6
grep -m1 "translucency changes make S" $OUT/gpu.log
for d in /tmp/r/*; do echo "### $d"; cat $d/*.md; done > $OUT/tables.md
