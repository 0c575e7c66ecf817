#!/usr/bin/env bash
# Issue 16's GPU figures on a lent GPU machine, within one call of the device tool: the batched ego env
# with its NPC model on CUDA (default guarded Trajeglish NPCs, 24 agents per scene) at each of BATCHES
# scenes, and highway-env in the same run for the ratios (`trajeglish bench --sections env --device cuda`).
#
# Run from the repository root, carrying .whl (`make device-wheels`):
#   run(command="OUT=$OUT bash scripts/device_bench.sh", carry=[".whl"], timeout_s=...)
# Writes into $OUT: bench_gpu.json (the bench document, rewritten after every run: a bench stopped at
# MINUTES keeps the runs it finished, `complete` false), bench_gpu.txt (its summary), log.txt.
#
# Settings (environment variables; defaults in brackets):
#   OUT       where the results go [required; the device tool sets it]
#   BATCHES   scenes per batched env [1 128 1024]
#   MINUTES   the bench is stopped after this [8]
#   GUARD     on | off | both: the NPCs' guarded sampling [on]
#   DEVICE    cuda | cpu [cuda]; cpu (with QUICK=1: tiny workloads) is a dry run on any machine
#   SPLIT     also run the default NPCs with the scenes split over this many worker processes (GPU
#             workers spawned, each with its copy of the model on the GPU), at the batches >= 8; [none]
#   WHEELS SITE PYTHON   [.whl, /tmp/site, python3]
#
# The project builds, tests and runs without this script or a GPU (README "Speed").
set -euo pipefail

die() {
    echo "device_bench: ERROR: $*" >&2
    exit 2
}
say() { echo "device_bench: [$(printf '%4d' "$SECONDS") s] $*" >&2; }

[ -n "${OUT:-}" ] || die "OUT is not set: give the folder whose files come back (the device tool sets \$OUT)"
[ -f scripts/device_bench.sh ] && [ -d trajeglish_env ] || die "run me from the repository root"
BATCHES=${BATCHES:-1 128 1024}
MINUTES=${MINUTES:-8}
GUARD=${GUARD:-on}
DEVICE=${DEVICE:-cuda}
QUICK_ARGS=()
if [ "${QUICK:-0}" = 1 ]; then QUICK_ARGS=(--quick); fi
case $DEVICE in cuda | cpu) ;; *) die "DEVICE=$DEVICE: expected cuda or cpu" ;; esac
SPLIT_ARGS=(--no-split)
if [ -n "${SPLIT:-}" ]; then
    [[ $SPLIT =~ ^[0-9]+$ ]] && [ "$SPLIT" -ge 2 ] || die "SPLIT=$SPLIT: expected a number of worker processes >= 2"
    SPLIT_ARGS=(--split-processes "$SPLIT")
fi
WHEELS=${WHEELS:-.whl}
SITE=${SITE:-/tmp/site}
PYTHON=${PYTHON:-python3}
mkdir -p "$OUT"
exec > >(tee -a "$OUT/log.txt") 2>&1
export PYTHONUNBUFFERED=1 PYGAME_HIDE_SUPPORT_PROMPT=1
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"

# shellcheck source=scripts/device_packages.sh
. scripts/device_packages.sh
install_carried_wheels
if [ "$DEVICE" = cuda ]; then
    "$PYTHON" -c 'import torch; assert torch.cuda.is_available(); print("device_bench: torch", torch.__version__, "on", torch.cuda.get_device_name())' 2>/dev/null ||
        die "torch sees no CUDA device on this machine (DEVICE=cpu for a dry run)"
fi
say "bench: DEVICE=$DEVICE BATCHES=$BATCHES GUARD=$GUARD SPLIT=${SPLIT:-none} ${QUICK_ARGS[*]}, at most $MINUTES min"
# shellcheck disable=SC2086 # BATCHES is a list of numbers
rm -f "$OUT/bench_gpu.json"
rc=0
timeout --kill-after=20 "$((MINUTES * 60))" "$PYTHON" -m trajeglish_env.cli bench --sections env \
    --batches $BATCHES --guard "$GUARD" --device "$DEVICE" "${SPLIT_ARGS[@]}" "${QUICK_ARGS[@]}" --quiet --json \
    --out "$OUT/bench_gpu.json" >/dev/null || rc=$?
# the bench writes its document after every run: a stopped bench keeps the runs it finished
[ -f "$OUT/bench_gpu.json" ] || die "the bench failed or ran past $MINUTES min before its first run ended (exit code $rc; see log.txt)"
"$PYTHON" -c 'import json, sys
from trajeglish_env.benchmark.suite import summary_lines
print("\n".join(summary_lines(json.load(open(sys.argv[1])))))' "$OUT/bench_gpu.json" | tee "$OUT/bench_gpu.txt"
if [ "$rc" != 0 ]; then
    say "the bench stopped early (exit code $rc: 124 is the $MINUTES-minute limit); $OUT/bench_gpu.json holds the runs it finished"
    exit "$rc"
fi
say "done: $OUT/bench_gpu.json"
