#!/usr/bin/env bash
# Run the cases of experiments/refactor_equivalence.py for two versions of the package side by side,
# one process per case and version, and compare their histories.
#
#   experiments/equivalence_parallel.sh BEFORE OUT [JOBS]
#
# BEFORE: a folder holding the other version's `jaxfric/` package (e.g. a `git worktree` of an older
# commit); OUT: where the histories, logs, compare.csv and compare.txt go; JOBS: processes at a time
# (default: the number of cores). Both versions run on the CPU with one XLA thread each, on the same
# machine, so that their histories can agree bit for bit.
set -euo pipefail
before=$(cd "$1" && pwd); out=$2; jobs=${3:-$(nproc)}
here=$(cd "$(dirname "$0")/.." && pwd)
export py=${PYTHON:-python3} before here out
export JAX_PLATFORMS=cpu XLA_FLAGS="--xla_cpu_multi_thread_eigen=false" PYTHONUNBUFFERED=1
mkdir -p "$out/logs"
PYTHONPATH=$here $py "$here/experiments/refactor_equivalence.py" list > "$out/cases.txt"
run() {  # version case
  local path=$here
  [ "$1" = before ] && path=$before
  PYTHONPATH=$path $py "$here/experiments/refactor_equivalence.py" record "$out/$1" "$2" \
    > "$out/logs/$1-$2.log" 2>&1 || echo "$1 $2 failed" >> "$out/failures.txt"
}
export -f run
# The longest case (make_run) first.
(grep -x make_run "$out/cases.txt"; grep -vx make_run "$out/cases.txt") \
  | awk '{print "before", $0; print "after", $0}' | xargs -P "$jobs" -n 2 bash -c 'run "$0" "$1"'
PYTHONPATH=$here $py "$here/experiments/refactor_equivalence.py" compare "$out/before" "$out/after" \
  "$out/compare.csv" > "$out/compare.txt"
cat "$out/compare.txt"
