#!/usr/bin/env bash
# The vmapped friction sweep on a lent GPU (issue: batched sweeps), one call:
#   bash experiments/device_sweep.sh OUTDIR
# Uses the device image's own jax (no install): the package from the working tree on PYTHONPATH.
# Writes OUTDIR/log and one CSV per sweep (experiments/bench_sweep.py's row, with the device). Each
# later step starts only with time left before BUDGET_S (default 480) and is cut at it, so the whole
# script ends inside one device call.
set -u
out=${1:?usage: device_sweep.sh OUTDIR}
mkdir -p "$out"
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 MPLBACKEND=Agg
py=${PYTHON:-python3}
budget=${BUDGET_S:-480}
start=$(date +%s)

step() {  # step TITLE ARGS...: run bench_sweep.py with ARGS if at least 60 s are left
  local left=$(( budget - ($(date +%s) - start) ))
  if (( left < 60 )); then echo "== skipped ($left s left): $1"; return; fi
  echo "== $1 (at most $left s)"
  shift
  timeout "$left" $py experiments/bench_sweep.py "$@" || echo "== stopped: exit $?"
}

{
  nvidia-smi -L
  $py -c "import jax; print('jax', jax.__version__, jax.devices())"
  step "sweep of 16 (on a GPU by default: cyclic-reduction solve, chunk 512); 4 single runs" \
    --members 16 --singles 4 --csv "$out/sweep16.csv"
  step "one Newton iteration, 16 members, chunk 512" --members 16 --iteration --chunk 512
  step "sweep of 64; 16 single runs" --members 64 --singles 16 --csv "$out/sweep64.csv"
  step "sweep of 16 with the Thomas solve (the CPU's); 1 single run" \
    --members 16 --singles 1 --solver thomas --chunk 512 --csv "$out/sweep16_thomas.csv"
  echo "== done after $(( $(date +%s) - start )) s"
} 2>&1 | tee "$out/log"
