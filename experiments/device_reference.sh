#!/usr/bin/env bash
# Candidate runs for the Nine's total-error reference on a lent GPU (issue 5), all side by side, one call:
#   bash experiments/device_reference.sh OUTDIR
# Uses the device image's own jax (no install): the package from the working tree on PYTHONPATH.
# Tried once (2026-11-27, H200, 17 runs at once from 100 x 2 to 9600 x 6, 527 s): only the 100 x 2 run
# finished (31 s, against 16 s on one CPU core; its history equals the CPU's to 5e-12). Whether the 16
# other processes sharing the GPU or the single run's latency held the fine meshes back was not
# measured; the default ladder is now five runs, and each prints its progress (the log's tails).
# LADDER (default below) lists TEST:MESH:STEP triples; every run starts at once (compilation is CPU
# work on the host's 16 cores; how well the solves share the GPU is what the first try left open) and
# is cut at BUDGET_S (default 500) after the script's start; CHUNK sets the element chunk (the first
# try used 16384). Writes OUTDIR/log (one JSON line per finished run, with each run's
# stderr) and OUTDIR/runs.tar.gz.part-aa, -ab, ... (the run directories, experiments/reference_candidate.py's
# layout, in parts of 15 MB: the device returns files of at most 16 MiB; `cat runs.tar.gz.part-* | tar -xz`).
set -u
out=${1:?usage: device_reference.sh OUTDIR}
mkdir -p "$out"
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 MPLBACKEND=Agg XLA_PYTHON_CLIENT_PREALLOCATE=false
py=${PYTHON:-python3}
budget=${BUDGET_S:-500}
chunk=${CHUNK:-131072}
root=$(mktemp -d)
start=$(date +%s)
ladder=${LADDER:-"
nine_mu017:100x2:0.5
nine_mu017:1200x6:0.5 nine_mu000:1200x6:0.5
nine_mu017:2400x6:0.5 nine_mu000:2400x6:0.5
"}

{
  nvidia-smi -L 2>/dev/null || echo "no nvidia-smi"
  $py -c "import jax; print('jax', jax.__version__, jax.devices())"
  i=0
  for item in $ladder; do
    IFS=: read -r test mesh step <<<"$item"
    i=$((i + 1))
    ( t0=$(date +%s)
      timeout $(( budget - (t0 - start) )) $py experiments/reference_candidate.py "$test" --mesh "$mesh" \
        --step "$step" --root "$root" --chunk "$chunk" --progress >"$root/run$i.json" 2>"$root/run$i.err"
      echo "== $test $mesh x$step: exit $? after $(( $(date +%s) - t0 )) s" ) &
  done
  wait
  for f in "$root"/run*.json; do cat "$f"; done
  echo "== stderr of the runs"
  for f in "$root"/run*.err; do echo "-- $f"; tail -c 600 "$f"; echo; done
  echo "== done after $(( $(date +%s) - start )) s"
} 2>&1 | tee "$out/log"
tar -cz -C "$root" --exclude='*.png' $(cd "$root" && ls -d */ 2>/dev/null) | split -b 15M - "$out/runs.tar.gz.part-"
ls -la "$out"
