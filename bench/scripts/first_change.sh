#!/bin/bash
# The first translucency changes of a scene on a running translux-server, with and without
# the translucency preparation (docs/api.md#translucency-preparation).
#   bench/scripts/first_change.sh BUNDLES SCENE OBJECT PRESET load|request|off [BACKEND]
# Starts target/release/translux-server on 127.0.0.1:8931, waits for SCENE to load (and, with
# `load`, for its translucency to be ready), then times three changes of OBJECT's dipole
# scale over REST and prints the server's preparation log lines.
set -euo pipefail
BUNDLES=$1 SCENE=$2 OBJECT=$3 PRESET=$4 MODE=$5 BACKEND=${6:-cpu}
ADDR=127.0.0.1:8931
LOG=$(mktemp)
RUST_LOG=info target/release/translux-server --bundles "$BUNDLES" --addr $ADDR \
    --backend "$BACKEND" --prepare-translucency "$MODE" > "$LOG" 2>&1 &
PID=$!
trap 'kill $PID 2>/dev/null; rm -f "$LOG"' EXIT
# 503 while it loads.
until curl -sf $ADDR/api/v1/scenes/"$SCENE" > /dev/null; do sleep 0.2; done
T0=$(date +%s.%N)
if [ "$MODE" = load ]; then
    until curl -sf $ADDR/api/v1/scenes/"$SCENE" | grep -q '"state":"ready"'; do sleep 0.2; done
    echo "translucency ready $(echo "$(date +%s.%N) - $T0" | bc) s after the scene loaded"
fi
curl -sf $ADDR/api/v1/scenes/"$SCENE" | python3 -c 'import json,sys; print(json.load(sys.stdin)["translucency"])'
for s in 0.5 0.6 0.7; do
    BODY="{\"materials\": {\"$OBJECT\": {\"type\": \"translucent\", \"profile\": {\"type\": \"dipole\", \"preset\": \"$PRESET\", \"scale\": $s}}}}"
    curl -sf -o /dev/null -w "change to scale $s: HTTP %{http_code}, %{time_total} s\n" \
        -H 'content-type: application/json' -d "$BODY" $ADDR/api/v1/scenes/"$SCENE"/relight
done
grep -E "prepared|radial terms" "$LOG" | sed 's/^[^ ]* *//' | cut -c1-240
