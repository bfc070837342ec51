#!/bin/bash
# Submits a translux precompute to Slurm: K shards as a job array, then the merge, which
# starts only when every shard succeeded (--dependency=afterok). Prints the two job ids,
# "ARRAY_JOB MERGE_JOB"; follow them with squeue, stop them with scancel.
#
#   docker/slurm/submit.sh SCENE OUT K [translux-precompute flags...]
#
# SBATCH_ARGS: more sbatch arguments for both jobs, split on spaces (e.g.
# "--partition=gpu --account=lab --time=2:00:00"). The environment of precompute.sbatch
# (TRANSLUX_PRECOMPUTE, TRANSLUX_SHARD_TRIES, TRANSLUX_OUTCOME_DIR, TRANSLUX_PUBLISH) is
# passed on to the jobs.
set -euo pipefail
if [ $# -lt 3 ]; then
  echo "usage: $0 SCENE OUT K [translux-precompute flags...]" >&2
  exit 2
fi
K=$3
case "$K" in '' | 0 | *[!0-9]*) echo "K must be a number of shards above 0, got '$K'" >&2; exit 2 ;; esac
SCRIPT="$(cd "$(dirname "$0")" && pwd)/precompute.sbatch"
LOGS="$(dirname "$2")"
# shellcheck disable=SC2086 # SBATCH_ARGS is a list of arguments
ARRAY=$(sbatch --parsable ${SBATCH_ARGS:-} --array="0-$((K - 1))" \
  --output="$LOGS/slurm-%A_%a.out" "$SCRIPT" "$@")
ARRAY=${ARRAY%%;*}
# shellcheck disable=SC2086
MERGE=$(sbatch --parsable ${SBATCH_ARGS:-} --dependency="afterok:$ARRAY" --kill-on-invalid-dep=yes \
  --output="$LOGS/slurm-%j.out" "$SCRIPT" "$@") || {
  scancel "$ARRAY"
  exit 1
}
echo "$ARRAY ${MERGE%%;*}"
