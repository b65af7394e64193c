#!/usr/bin/env bash
# Submit a pipeline as N array tasks (cluster/slurm/shards.sbatch) and a
# merge job that starts when all of them succeeded (afterok).
#
#   cluster/slurm/submit-shards.sh PIPELINE N [matflow run options]
#
# Prints the two job ids. sbatch options go in $SBATCH_OPTIONS (e.g.
# "--partition=render --cpus-per-task=8"); the environment of shards.sbatch
# (MATFLOW_BIN, MATFLOW_REMOTE_CACHE, MATFLOW_REPORT_DIR) passes through.
set -euo pipefail
[ $# -ge 2 ] || { echo "usage: $0 PIPELINE N [matflow run options]" >&2; exit 2; }
here="$(cd "$(dirname "$0")" && pwd)"
pipeline="$1"
n="$2"
shift 2
[[ "$n" =~ ^[1-9][0-9]*$ ]] || { echo "N must be a positive integer, not '$n'" >&2; exit 2; }
# shellcheck disable=SC2086
array="$(MATFLOW_SHARDS="$n" sbatch --parsable ${SBATCH_OPTIONS:-} --array="0-$((n - 1))" \
    "$here/shards.sbatch" "$pipeline" "$@")"
array="${array%%;*}"
# shellcheck disable=SC2086
merge="$(sbatch --parsable ${SBATCH_OPTIONS:-} --dependency="afterok:$array" --kill-on-invalid-dep=yes \
    "$here/merge.sbatch" "$pipeline" "$@")"
echo "shards: job $array (array 0-$((n - 1))); merge: job ${merge%%;*} (after all shards succeed)"
