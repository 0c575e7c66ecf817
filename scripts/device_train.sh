#!/usr/bin/env bash
# Train Trajeglish on a lent GPU machine within one call of the device tool, and bring the checkpoint back.
#
# Run from the repository root. In order: install the wheels carried in .whl/ (`make device-wheels`) into
# /tmp/site when a package is missing; print Python, torch, CUDA and the GPU (and stop with one clear line
# when the job cannot run: no CUDA, a missing package and which wheel to carry); generate highway-env
# scenes (and SUMO scenes where SUMO is installed) with every core for at most GEN_MINUTES; train with
# `trajeglish train` on CUDA until the call's budget is nearly spent, checkpointing often, resuming the
# run carried in RUN_IN when there is one; and write into $OUT what the device tool brings back:
#   $OUT/model.pt            the trained checkpoint (trajeglish_env.checkpoint.load_checkpoint)
#   $OUT/summary.json        held-out NLL, step, training curve, one record per call, files
#   $OUT/metrics.csv, $OUT/training_curve.png, $OUT/log.txt
#   $OUT/resume/             last.pt (weights + optimizer) in 15 MiB parts and run.json: copy it to
#                            .devrun/ and carry it with RUN_IN=.devrun to continue in the next call
#
# Settings (environment variables; defaults in brackets):
#   OUT            where the results go [required; the device tool sets it]
#   DEVICE         cuda | cpu [cuda]; cpu is a dry run here (CUDA is then hidden even where present)
#   MINUTES        wall-clock budget of the whole job, set-up to packing [9: inside one 10-minute call]
#   TRAIN_MINUTES  training budget [what MINUTES leaves after generation, less MARGIN_S]
#   MARGIN_S       seconds kept for starting train, the last validation, saving and packing
#                  [MINUTES*15 within 15..45]
#   PRESET         model size: tiny | small [small; with INIT the checkpoint's model, a resumed run its own];
#                  paper's checkpoint is too big to come back
#   SCENES         highway-env training scenes to generate at most (0: none) [4000]
#   GEN_MINUTES    generation stops after this, keeping the finished shards [1.5]
#   SUMO_SCENES    SUMO scenes to generate: auto (SCENES/4 where SUMO is installed, else none) | N [auto]
#   STOP_SCENES    highway-env scenes with a hard stop event (every `KIND+stop` kind: a vehicle brakes to a
#                  stop in front of a follower) generated beside the others, seed GEN_SEED + 5000 [0]
#   VAL_SCENES     held-out highway-env scenes (fixed seed VAL_SEED, the same in every call) [SCENES/20
#                  within 8..64]; 0: hold out every 20th training scene instead
#   DATA_IN        carried scenes: DATA_IN/train/** is trained on, DATA_IN/val/** held out
#                  [.devdata when it exists; `make device-sumo-scenes` fills it with SUMO scenes]
#   RUN_IN         a previous call's $OUT/resume folder (carried) to continue [none: a new run]
#   INIT           a new run starts from this checkpoint ('shipped': the shipped model; fine-tuning, its
#                  config and vocabulary) [none: random weights]; a resumed run keeps its own start
#   GEN_SEED       seed of this call's scenes [1000 + the number of earlier calls of the run]
#   SIGNAL_INPUT   1: the model reads traffic-signal states (`train --signal-input`; with INIT, the
#                  checkpoint's model extended with that input) [0]
#   SIGNAL_LR_SCALE  learning-rate multiplier of the signal embedding (`--signal-lr-scale`) [1]
#   NEIGHBOUR_INPUT  1: every decoder position reads its agent's velocity and nearest neighbours' relative
#                  states (`train --neighbour-input`; with INIT, the checkpoint's model extended with it) [0]
#   LANE_INPUT     1: every decoder position reads the lane centres and road edges around its agent in the
#                  agent's frame (`train --lane-input`; with INIT, the checkpoint's model extended with it) [0]
#   VOCAB          a new run without INIT: fit a vocabulary of this many tokens per class on the
#                  training scenes (`tokenizer fit`, with its motion-envelope cover) and train on it; 0:
#                  the shipped 384 [0]. The README's choice for a model trained from scratch:
#                  VOCAB=1024 COVER_RADIUS=0.03 DATA_SHARE=0.2 (envelope tracks within 5 cm)
#   COVER_RADIUS DATA_SHARE   that fit's `--cover-radius` and `--data-share` [0.045, 0.5]
#   EXTEND         a new run with INIT: extend the checkpoint's vocabulary to this many tokens per class
#                  (`tokenizer extend`: old tokens kept, the added ones cover every motion of the env's
#                  limits; EXTEND=2048 keeps them within 5 cm) and fine-tune on it; 0: keep it [0]. A
#                  carried DATA_IN/vocab_extended_EXTEND.npz (`make device-vocab`) that extends INIT's
#                  vocabulary to EXTEND tokens is used as it is (the extension is deterministic: half a
#                  minute of the call saved)
#   MAP_SELECT     frame | agents | ahead: a window's map chunks nearest its frame agent, any of its agents, or
#                  those and where each drives to in 0.8 / 1.6 / 2.4 s
#                  (`train --map-select`; with INIT it may differ from the checkpoint's) [the checkpoint's,
#                  or frame]
#   MAP_STRIDE     a map chunk takes every Nth point of its polyline (`train --map-stride`; 4: chunks 38 m
#                  long instead of 9.5 m; with INIT it may differ from the checkpoint's) [the checkpoint's, or 1]
#   STEPS BATCH LR WARMUP SEED VAL_EVERY CKPT_EVERY   the run's schedule [10000 32 5e-4 200 0 500 250];
#                  kept from RUN_IN when resuming (setting another value is an error), as the SIGNAL_ ones are.
#   REPEAT         scene kinds drawn N times an epoch, e.g. "sumo=3 highway/roundabout=2" (`train --repeat`;
#                  SUMO's share when only highway-env scenes are generated here) [none]; kept when resuming
#   CLOSED_LOOP    K >= 1: CAT-K closed-loop fine-tuning (`train --closed-loop-top-k K`: each batch is first
#                  rolled out by the model, its K most likely tokens nearest the log, and trained to return
#                  to the log, beside its teacher-forced windows); use with INIT; 0: teacher forcing [0];
#                  kept when resuming
#   INTERACTION_WEIGHT  loss weight of the tokens of agents closing in on the agent ahead (`train
#                  --interaction-weight`; docs/evaluation.md "Weighing the tokens of followers that close
#                  in"); 1: plain likelihood [1]; kept when resuming
#   BEND_WEIGHT    loss weight of the tokens where the lane ahead turns away from an agent's current motion
#                  (`train --bend-weight`; docs/evaluation.md "Weighing the tokens where the road bends");
#                  needs LANE_INPUT=1; 1: plain likelihood [1]; kept when resuming
#   COLLISION_WEIGHT  weight of the loss term against the probability on colliding candidate tokens (`train
#                  --collision-weight`; docs/evaluation.md "The model alone collides by its own draws");
#                  scenes of a model's own rollouts carried in DATA_IN/train (`scripts/guarded_rollout_scenes.py
#                  --guard off --as-rollout`) train by it alone past their current step; 0: off [0]; kept
#                  when resuming
#   COLLISION_HORIZON  steps each candidate is kept up for COLLISION_WEIGHT (`train --collision-horizon`):
#                  1: the guard's one-step rule [1]; kept when resuming
#   COLLISION_ROLLED_OUT_ONLY  1: COLLISION_WEIGHT on the rolled-out targets of own-rollout scenes alone
#                  (`train --collision-rolled-out-only`; the logged targets keep plain likelihood) [0]; kept
#                  when resuming
#   COLLISION_SOURCES  space-separated scene sources whose windows COLLISION_WEIGHT acts on alone (`train
#                  --collision-sources`, e.g. sumo; own rollouts of a source count as it); empty: every window
#                  []; kept when resuming
#   COLLISION_FORM  the form of COLLISION_WEIGHT's term (`train --collision-form`): mass (-log(1 - m) of the
#                  colliding mass) or versus-target (log(1 + m / p), p the target token's probability) [mass];
#                  kept when resuming
#   OFFROAD_WEIGHT  weight of the loss term against the probability on candidate tokens that would take a
#                  vehicle off the road (`train --offroad-weight`; the guard's road-edge rule); 0: off [0];
#                  kept when resuming
#   OFFROAD_FORM   the form of OFFROAD_WEIGHT's term (`train --offroad-form`), as COLLISION_FORM [mass];
#                  kept when resuming
#   OFFROAD_HORIZON  steps a candidate's move is kept up for OFFROAD_WEIGHT's rule (`train
#                  --offroad-horizon`; needs OFFROAD_WEIGHT > 0) [1]; kept when resuming
#   HISTORY_DROPOUT  share of each window's agents whose input tokens are all hidden (`train
#                  --history-dropout`; needs NEIGHBOUR_INPUT=1; docs/evaluation.md "Hiding an agent's own
#                  motion"); 0: none [0]; kept when resuming
#   FIT_STEPS      1: the first call's step rate fits the schedule's length to its training budget (`train
#                  --fit-steps`; STEPS is then the most), so the learning rate reaches 0 as that call ends;
#                  0: the schedule runs STEPS, over as many calls as it takes (RUN_IN) [1]
#   GEN_WORKERS TRAIN_WORKERS   processes generating / loading batches [cores, cores - 1]
#   NOISE_ON_DEVICE  1: the noisy input tokens are drawn in the training process on the GPU (`train
#                  --noise-on-device`; the loaders then only tokenize by argmin), after a check that the draw
#                  there agrees with the loaders' (else they keep drawing it); 0: the loaders; auto: 1 on
#                  cuda [auto]
#   WHEELS SITE WORK PYTHON     [.whl, /tmp/site, /tmp/trajeglish_device, python3]
#
# The project builds, tests and runs without this script or a GPU; see README "Training on a GPU machine".
set -euo pipefail

die() {
    echo "device_train: ERROR: $*" >&2
    exit 2
}
say() { echo "device_train: [$(printf '%4d' "$SECONDS") s] $*" >&2; }
calc() { awk "BEGIN { print $* }"; }

[ -n "${OUT:-}" ] || die "OUT is not set: give the folder whose files come back (the device tool sets \$OUT)"
[ -f scripts/device_train.sh ] && [ -d trajeglish_env ] || die "run me from the repository root"
REPO=$PWD
command -v timeout >/dev/null || die "coreutils' timeout is missing"

# user-set schedule values (checked against a resumed run's before defaults fill the rest); a resumed run
# keeps these (trajeglish_env/device_job.py SAVED)
SAVED_VARS="PRESET STEPS BATCH LR WARMUP SEED VAL_EVERY CKPT_EVERY SIGNAL_INPUT SIGNAL_LR_SCALE NEIGHBOUR_INPUT LANE_INPUT VOCAB EXTEND COVER_RADIUS DATA_SHARE MAP_SELECT MAP_STRIDE FIT_STEPS REPEAT CLOSED_LOOP INTERACTION_WEIGHT BEND_WEIGHT COLLISION_WEIGHT COLLISION_HORIZON COLLISION_ROLLED_OUT_ONLY COLLISION_SOURCES COLLISION_FORM OFFROAD_WEIGHT OFFROAD_FORM OFFROAD_HORIZON HISTORY_DROPOUT"
declare -A GIVEN=()
for v in $SAVED_VARS; do
    if [ -n "${!v:-}" ]; then GIVEN[$v]=${!v}; fi
done

DEVICE=${DEVICE:-cuda}
MINUTES=${MINUTES:-9}
SCENES=${SCENES:-4000}
GEN_MINUTES=${GEN_MINUTES:-1.5}
SUMO_SCENES=${SUMO_SCENES:-auto}
STOP_SCENES=${STOP_SCENES:-0}
[[ "$STOP_SCENES" =~ ^[0-9]+$ ]] || die "STOP_SCENES=$STOP_SCENES: expected a whole number of scenes"
VAL_SEED=${VAL_SEED:-90001}
WHEELS=${WHEELS:-.whl}
SITE=${SITE:-/tmp/site}
WORK=${WORK:-/tmp/trajeglish_device}
PYTHON=${PYTHON:-python3}
RUN_IN=${RUN_IN:-}
if [ -z "${DATA_IN+x}" ] && [ -d .devdata ]; then DATA_IN=.devdata; fi
DATA_IN=${DATA_IN:-}
MARGIN_S=${MARGIN_S:-$(calc "int(($MINUTES * 15 < 15) ? 15 : (($MINUTES * 15 > 45) ? 45 : $MINUTES * 15))")}
case $DEVICE in
cuda) ;;
cpu) export CUDA_VISIBLE_DEVICES="" ;;
*) die "DEVICE=$DEVICE: expected cuda or cpu" ;;
esac

STALE=0
[ ! -d "$WORK/data" ] || STALE=1 # scenes of an earlier job: generate resumes them or refuses to mix
mkdir -p "$OUT" "$WORK"
LOG=$WORK/log.txt
: >"$LOG"
exec > >(tee -a "$LOG") 2>&1
[ "$STALE" = 0 ] || echo "device_train: WORK=$WORK holds scenes of an earlier job (reused where they match; scenes of another generator version are refused and stop the job): set WORK to a fresh folder to start clean" >&2
export PYTHONUNBUFFERED=1 PYGAME_HIDE_SUPPORT_PROMPT=1
export PYTHONPATH="$REPO${PYTHONPATH:+:$PYTHONPATH}"
say "job: DEVICE=$DEVICE MINUTES=$MINUTES SCENES=$SCENES OUT=$OUT WORK=$WORK RUN_IN=${RUN_IN:-none} DATA_IN=${DATA_IN:-none} INIT=${INIT:-none}"

# ---- 1. the run: new, or carried in RUN_IN (its settings are checked before anything slow)
RUN=$WORK/run
rm -rf "$RUN"
CALL=0
RESUME=()
if [ -n "$RUN_IN" ]; then
    SAVED=$("$PYTHON" trajeglish_env/device_job.py saved "$RUN_IN") || exit 2
    eval "$SAVED"
    for v in $SAVED_VARS; do
        s=SAVED_$v
        [ -n "${!s:-}" ] || continue
        if [ -n "${GIVEN[$v]:-}" ] && [ "${GIVEN[$v]}" != "${!s}" ]; then
            die "$v=${GIVEN[$v]} but the run in RUN_IN was started with $v=${!s}: a resumed run keeps its schedule (unset $v, or start a new run without RUN_IN)"
        fi
        printf -v "$v" '%s' "${!s}"
    done
    RESUME=(--resume)
fi
INIT_ARGS=()
if [ -n "${INIT:-}" ]; then
    if [ -n "$RUN_IN" ]; then
        say "INIT=$INIT ignored: the run in RUN_IN goes on from its own checkpoint"
    elif [ "$INIT" != shipped ] && [ ! -f "$INIT" ]; then
        die "INIT=$INIT: no such checkpoint file (carry it, or use INIT=shipped)"
    else
        INIT_ARGS=(--init "$INIT")
    fi
fi
PRESET=${PRESET:-small}
STEPS=${STEPS:-10000}
BATCH=${BATCH:-32}
LR=${LR:-5e-4}
WARMUP=${WARMUP:-200}
SEED=${SEED:-0}
VAL_EVERY=${VAL_EVERY:-500}
CKPT_EVERY=${CKPT_EVERY:-250}
SIGNAL_INPUT=${SIGNAL_INPUT:-0}
SIGNAL_LR_SCALE=${SIGNAL_LR_SCALE:-1}
NEIGHBOUR_INPUT=${NEIGHBOUR_INPUT:-0}
LANE_INPUT=${LANE_INPUT:-0}
VOCAB=${VOCAB:-0}
EXTEND=${EXTEND:-0}
NOISE_ON_DEVICE=${NOISE_ON_DEVICE:-auto}
case $NOISE_ON_DEVICE in 0 | 1 | auto) ;; *) die "NOISE_ON_DEVICE=$NOISE_ON_DEVICE: expected 0, 1 or auto" ;; esac
COVER_RADIUS=${COVER_RADIUS:-0.045}
DATA_SHARE=${DATA_SHARE:-0.5}
MAP_SELECT=${MAP_SELECT:-}
MAP_STRIDE=${MAP_STRIDE:-}
FIT_STEPS=${FIT_STEPS:-1}
REPEAT=${REPEAT:-}
CLOSED_LOOP=${CLOSED_LOOP:-0}
case $CLOSED_LOOP in
'' | *[!0-9]*) die "CLOSED_LOOP=$CLOSED_LOOP: expected a number of tokens K (0: teacher forcing)" ;;
esac
CLOSED_ARGS=()
[ "$CLOSED_LOOP" = 0 ] || CLOSED_ARGS=(--closed-loop-top-k "$CLOSED_LOOP")
INTERACTION_WEIGHT=${INTERACTION_WEIGHT:-1}
[[ "$INTERACTION_WEIGHT" =~ ^[0-9]+([.][0-9]+)?$ ]] && [ "$(calc "($INTERACTION_WEIGHT >= 1)")" = 1 ] ||
    die "INTERACTION_WEIGHT=$INTERACTION_WEIGHT: expected a loss weight >= 1 (1: plain likelihood)"
[ "$INTERACTION_WEIGHT" = 1 ] || CLOSED_ARGS+=(--interaction-weight "$INTERACTION_WEIGHT")
BEND_WEIGHT=${BEND_WEIGHT:-1}
[[ "$BEND_WEIGHT" =~ ^[0-9]+([.][0-9]+)?$ ]] && [ "$(calc "($BEND_WEIGHT >= 1)")" = 1 ] ||
    die "BEND_WEIGHT=$BEND_WEIGHT: expected a loss weight >= 1 (1: plain likelihood)"
[ "$BEND_WEIGHT" = 1 ] || CLOSED_ARGS+=(--bend-weight "$BEND_WEIGHT")
COLLISION_WEIGHT=${COLLISION_WEIGHT:-0}
[[ "$COLLISION_WEIGHT" =~ ^[0-9]+([.][0-9]+)?$ ]] ||
    die "COLLISION_WEIGHT=$COLLISION_WEIGHT: expected a loss weight >= 0 (0: off)"
[ "$(calc "($COLLISION_WEIGHT > 0)")" = 0 ] || CLOSED_ARGS+=(--collision-weight "$COLLISION_WEIGHT")
COLLISION_HORIZON=${COLLISION_HORIZON:-1}
[[ "$COLLISION_HORIZON" =~ ^[1-9][0-9]*$ ]] ||
    die "COLLISION_HORIZON=$COLLISION_HORIZON: expected a whole number of steps >= 1"
[ "$COLLISION_HORIZON" = 1 ] || CLOSED_ARGS+=(--collision-horizon "$COLLISION_HORIZON")
COLLISION_ROLLED_OUT_ONLY=${COLLISION_ROLLED_OUT_ONLY:-0}
case $COLLISION_ROLLED_OUT_ONLY in
0) ;;
1) CLOSED_ARGS+=(--collision-rolled-out-only) ;;
*) die "COLLISION_ROLLED_OUT_ONLY=$COLLISION_ROLLED_OUT_ONLY: expected 0 or 1" ;;
esac
COLLISION_SOURCES=${COLLISION_SOURCES:-}
if [ -n "$COLLISION_SOURCES" ]; then
    [[ "$COLLISION_SOURCES" =~ ^[a-z0-9_]+( [a-z0-9_]+)*$ ]] ||
        die "COLLISION_SOURCES=$COLLISION_SOURCES: expected scene sources separated by spaces, such as sumo"
    read -r -a COLLISION_SOURCE_LIST <<<"$COLLISION_SOURCES"
    CLOSED_ARGS+=(--collision-sources "${COLLISION_SOURCE_LIST[@]}")
fi
COLLISION_FORM=${COLLISION_FORM:-mass}
case $COLLISION_FORM in
mass) ;;
versus-target) CLOSED_ARGS+=(--collision-form versus-target) ;;
*) die "COLLISION_FORM=$COLLISION_FORM: expected mass or versus-target" ;;
esac
OFFROAD_WEIGHT=${OFFROAD_WEIGHT:-0}
[[ "$OFFROAD_WEIGHT" =~ ^[0-9]+([.][0-9]+)?$ ]] ||
    die "OFFROAD_WEIGHT=$OFFROAD_WEIGHT: expected a loss weight >= 0 (0: off)"
[ "$(calc "($OFFROAD_WEIGHT > 0)")" = 0 ] || CLOSED_ARGS+=(--offroad-weight "$OFFROAD_WEIGHT")
OFFROAD_FORM=${OFFROAD_FORM:-mass}
case $OFFROAD_FORM in
mass) ;;
versus-target) CLOSED_ARGS+=(--offroad-form versus-target) ;;
*) die "OFFROAD_FORM=$OFFROAD_FORM: expected mass or versus-target" ;;
esac
OFFROAD_HORIZON=${OFFROAD_HORIZON:-1}
[[ "$OFFROAD_HORIZON" =~ ^[1-9][0-9]*$ ]] || die "OFFROAD_HORIZON=$OFFROAD_HORIZON: expected steps >= 1"
if [ "$OFFROAD_HORIZON" != 1 ]; then
    [ "$(calc "($OFFROAD_WEIGHT > 0)")" = 1 ] || die "OFFROAD_HORIZON=$OFFROAD_HORIZON needs OFFROAD_WEIGHT > 0"
    CLOSED_ARGS+=(--offroad-horizon "$OFFROAD_HORIZON")
fi
HISTORY_DROPOUT=${HISTORY_DROPOUT:-0}
[[ "$HISTORY_DROPOUT" =~ ^0*([.][0-9]+)?$ ]] && [ "$(calc "($HISTORY_DROPOUT < 1)")" = 1 ] ||
    die "HISTORY_DROPOUT=$HISTORY_DROPOUT: expected a share in [0, 1) (0: none)"
[ "$(calc "($HISTORY_DROPOUT > 0)")" = 0 ] || CLOSED_ARGS+=(--history-dropout "$HISTORY_DROPOUT")
REPEAT_ARGS=()
# shellcheck disable=SC2206 # REPEAT is a list of KIND=N words
[ -z "$REPEAT" ] || REPEAT_ARGS=(--repeat $REPEAT)
case $FIT_STEPS in
0) FIT_ARGS=() ;;
1) FIT_ARGS=(--fit-steps) ;;
*) die "FIT_STEPS=$FIT_STEPS: expected 0 or 1" ;;
esac
MAP_ARGS=()
case $MAP_SELECT in
'') ;;
frame | agents | ahead) MAP_ARGS=(--map-select "$MAP_SELECT") ;;
*) die "MAP_SELECT=$MAP_SELECT: expected frame, agents or ahead" ;;
esac
case $MAP_STRIDE in
'') ;;
*[!0-9]* | 0) die "MAP_STRIDE=$MAP_STRIDE: expected a whole number >= 1" ;;
*) MAP_ARGS+=(--map-stride "$MAP_STRIDE") ;;
esac
case $VOCAB in
'' | *[!0-9]*) die "VOCAB=$VOCAB: expected a number of tokens (0: the shipped vocabulary)" ;;
esac
case $EXTEND in
'' | *[!0-9]*) die "EXTEND=$EXTEND: expected a number of tokens (0: the checkpoint's vocabulary)" ;;
esac
[ "$EXTEND" = 0 ] || [ -n "$RUN_IN" ] || [ ${#INIT_ARGS[@]} != 0 ] || die "EXTEND=$EXTEND needs INIT: it extends the checkpoint's vocabulary"
[ "$VOCAB" = 0 ] || [ ${#INIT_ARGS[@]} = 0 ] || die "VOCAB=$VOCAB with INIT=$INIT: a fine-tuned model keeps its checkpoint's vocabulary (unset one of them)"
case $SIGNAL_INPUT in
0) SIGNAL_ARGS=() ;;
1) SIGNAL_ARGS=(--signal-input --signal-lr-scale "$SIGNAL_LR_SCALE") ;;
*) die "SIGNAL_INPUT=$SIGNAL_INPUT: expected 0 or 1" ;;
esac
case $NEIGHBOUR_INPUT in
0) ;;
1) SIGNAL_ARGS+=(--neighbour-input) ;;
*) die "NEIGHBOUR_INPUT=$NEIGHBOUR_INPUT: expected 0 or 1" ;;
esac
case $LANE_INPUT in
0) ;;
1) SIGNAL_ARGS+=(--lane-input) ;;
*) die "LANE_INPUT=$LANE_INPUT: expected 0 or 1" ;;
esac
[ "$(calc "($HISTORY_DROPOUT > 0)")" = 0 ] || [ "$NEIGHBOUR_INPUT" = 1 ] ||
    die "HISTORY_DROPOUT=$HISTORY_DROPOUT needs NEIGHBOUR_INPUT=1 (a dropped agent's next tokens are told from its neighbours)"
[ "$BEND_WEIGHT" = 1 ] || [ "$LANE_INPUT" = 1 ] ||
    die "BEND_WEIGHT=$BEND_WEIGHT needs LANE_INPUT=1 (the bends are found in the lane points the model reads)"
GEN_SEED=${GEN_SEED:-$((1000 + CALL))}
[ "$PRESET" != paper ] || die "PRESET=paper: its checkpoint (about 170 MB, 520 MB with the optimizer) cannot come back (8 files of 16 MiB); use small"
say "run: call $CALL, PRESET=$PRESET STEPS=$STEPS BATCH=$BATCH LR=$LR WARMUP=$WARMUP SEED=$SEED SIGNAL_INPUT=$SIGNAL_INPUT SIGNAL_LR_SCALE=$SIGNAL_LR_SCALE NEIGHBOUR_INPUT=$NEIGHBOUR_INPUT LANE_INPUT=$LANE_INPUT VOCAB=$VOCAB EXTEND=$EXTEND COVER_RADIUS=$COVER_RADIUS DATA_SHARE=$DATA_SHARE MAP_SELECT=$MAP_SELECT MAP_STRIDE=$MAP_STRIDE FIT_STEPS=$FIT_STEPS REPEAT="$REPEAT" CLOSED_LOOP=$CLOSED_LOOP INTERACTION_WEIGHT=$INTERACTION_WEIGHT BEND_WEIGHT=$BEND_WEIGHT COLLISION_WEIGHT=$COLLISION_WEIGHT COLLISION_HORIZON=$COLLISION_HORIZON COLLISION_ROLLED_OUT_ONLY=$COLLISION_ROLLED_OUT_ONLY COLLISION_SOURCES="$COLLISION_SOURCES" COLLISION_FORM=$COLLISION_FORM OFFROAD_WEIGHT=$OFFROAD_WEIGHT OFFROAD_FORM=$OFFROAD_FORM OFFROAD_HORIZON=$OFFROAD_HORIZON HISTORY_DROPOUT=$HISTORY_DROPOUT, scenes seed $GEN_SEED"

# ---- 2. packages: the carried wheels, installed only when something is missing
# shellcheck source=scripts/device_packages.sh
. scripts/device_packages.sh
install_carried_wheels

# ---- 3. the machine (and the carried run's checkpoint, rebuilt from its parts)
REBUILD=()
[ -z "$RUN_IN" ] || REBUILD=(--resume "$RUN_IN" "$RUN")
CHECK=$("$PYTHON" trajeglish_env/device_job.py check --device "$DEVICE" --sumo "$SUMO_SCENES" "${REBUILD[@]}") ||
    exit 2
eval "$CHECK"
[ "$DEVICE" = cuda ] && command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | sed 's/^/device_train: nvidia-smi: /' || true
GEN_WORKERS=${GEN_WORKERS:-$CORES}
TRAIN_WORKERS=${TRAIN_WORKERS:-$((CORES > 1 ? CORES - 1 : 0))}

# ---- 4. scenes: highway-env (and SUMO) on every core, for at most GEN_MINUTES
DATA=$WORK/data
[ -z "$DATA_IN" ] || [ -d "$DATA_IN" ] || die "DATA_IN=$DATA_IN: no such folder (carry it: carry [\"$DATA_IN\"])"
VAL_SCENES=${VAL_SCENES:-$(calc "int(($SCENES / 20 < 8) ? 8 : (($SCENES / 20 > 64) ? 64 : $SCENES / 20))")}
gen() { # source scenes seed out workers seconds [kinds]: finished shards stay when the time is up
    local rc=0 kinds=()
    [ -z "${7:-}" ] || kinds=(--kinds "$7")
    mkdir -p "$(dirname "$4")"
    timeout --kill-after=15 "$6" "$PYTHON" -m trajeglish_env.cli generate --quiet --source "$1" \
        --scenes "$2" --seed "$3" --out "$4" --workers "$5" "${kinds[@]}" >/dev/null 2>"$4.err" || rc=$?
    cat "$4.err" >&2
    ! grep -q "refusing" "$4.err" || die "generate --source $1 --out $4 refused its folder (see $LOG)"
    [ "$rc" = 0 ] || [ "$rc" = 124 ] || die "generate --source $1 --out $4 failed (exit code $rc)"
    [ "$rc" = 0 ] || say "$(basename "$4"): time is up after $6 s; keeping the finished shards"
}
shards() { find "$@" -name '*.scn.npz' ! -name '.*' | wc -l; } # shard files under folders
if [ "$SUMO_SCENES" = auto ]; then
    SUMO_SCENES=$((SUMO_OK ? SCENES / 4 : 0))
    [ "$SUMO_OK" = 1 ] || say "SUMO is not installed here: no SUMO scenes generated (carry some in DATA_IN: make device-sumo-scenes)"
fi
# generation may take GEN_MINUTES, and at most half of what the budget leaves
GEN_S=$(calc "int(($GEN_MINUTES * 60 < ($MINUTES * 60 - $SECONDS - $MARGIN_S) / 2) ? $GEN_MINUTES * 60 : ($MINUTES * 60 - $SECONDS - $MARGIN_S) / 2)")
[ "$GEN_S" -ge 5 ] || GEN_S=5
T_GEN=$SECONDS
TRAIN_DIRS=()
VAL_DIR=
PIDS=()
if [ "$VAL_SCENES" -gt 0 ]; then # the same held-out scenes in every call of a run (fixed seed)
    VAL_GEN=$DATA/val-highway-s$VAL_SEED-n$VAL_SCENES
    gen highway "$VAL_SCENES" "$VAL_SEED" "$VAL_GEN" "$(((GEN_WORKERS + 3) / 4))" "$GEN_S" &
    PIDS+=($!)
fi
if [ "$SCENES" -gt 0 ]; then
    TRAIN_DIRS+=("$DATA/highway-s$GEN_SEED-n$SCENES")
    HW_WORKERS=$((SUMO_SCENES > 0 ? (GEN_WORKERS * 3 + 3) / 4 : GEN_WORKERS))
    gen highway "$SCENES" "$GEN_SEED" "${TRAIN_DIRS[-1]}" "$HW_WORKERS" "$GEN_S" &
    PIDS+=($!)
fi
if [ "$SUMO_SCENES" -gt 0 ]; then
    TRAIN_DIRS+=("$DATA/sumo-s$GEN_SEED-n$SUMO_SCENES")
    gen sumo "$SUMO_SCENES" "$GEN_SEED" "${TRAIN_DIRS[-1]}" "$(((GEN_WORKERS + 3) / 4))" "$GEN_S" &
    PIDS+=($!)
fi
if [ "$STOP_SCENES" -gt 0 ]; then
    STOP_KINDS=$("$PYTHON" -c "from trajeglish_env.sources.highway import EXTRA_KINDS; print(','.join(EXTRA_KINDS))")
    TRAIN_DIRS+=("$DATA/stop-s$((GEN_SEED + 5000))-n$STOP_SCENES")
    gen highway "$STOP_SCENES" "$((GEN_SEED + 5000))" "${TRAIN_DIRS[-1]}" "$(((GEN_WORKERS + 3) / 4))" "$GEN_S" "$STOP_KINDS" &
    PIDS+=($!)
fi
for pid in "${PIDS[@]}"; do wait "$pid" || exit 2; done
if [ "$VAL_SCENES" -gt 0 ]; then
    VAL_DIR=$WORK/val
    rm -rf "$VAL_DIR"
    mkdir -p "$VAL_DIR" && cp -r "$VAL_GEN" "$VAL_DIR/highway"
    [ -z "$DATA_IN" ] || [ ! -d "$DATA_IN/val" ] || cp -r "$DATA_IN/val" "$VAL_DIR/carried"
fi
[ -z "$DATA_IN" ] || [ ! -d "$DATA_IN/train" ] || TRAIN_DIRS+=("$DATA_IN/train")
HAVE=()
for d in "${TRAIN_DIRS[@]}"; do if [ -d "$d" ]; then HAVE+=("$d"); fi; done
[ "${#HAVE[@]}" -gt 0 ] || die "no training scenes: raise SCENES or GEN_MINUTES, or carry DATA_IN"
N_TRAIN=$(shards "${HAVE[@]}")
[ "$N_TRAIN" -gt 0 ] || die "no training scene was finished in the $GEN_S s given to generation: raise MINUTES or GEN_MINUTES, or carry DATA_IN"
N_VAL=0
[ -z "$VAL_DIR" ] || N_VAL=$(shards "$VAL_DIR")
if [ -n "$VAL_DIR" ] && [ "$N_VAL" = 0 ]; then
    say "no held-out scene was finished in time: holding out every 20th training scene instead"
    VAL_DIR=
fi
GEN_TOOK=$((SECONDS - T_GEN))
say "scene shards: $N_TRAIN for training (${HAVE[*]}), $N_VAL held out; $GEN_TOOK s"

# ---- 5. a new vocabulary (VOCAB, new runs only: a resumed run's checkpoint holds its own)
VOCAB_ARGS=()
if [ "$VOCAB" != 0 ] && [ -z "$RUN_IN" ]; then
    T_VOCAB=$SECONDS
    "$PYTHON" -m trajeglish_env.cli tokenizer fit --json --data "${HAVE[@]}" --vocab "$VOCAB" --trials 2 \
        --cover-radius "$COVER_RADIUS" --data-share "$DATA_SHARE" --out "$WORK/vocab.npz" >"$WORK/vocab.json" || die "tokenizer fit --vocab $VOCAB failed (see $LOG)"
    VOCAB_ARGS=(--vocab "$WORK/vocab.npz")
    say "fitted a $VOCAB-token vocabulary on the training scenes in $((SECONDS - T_VOCAB)) s"
fi
if [ "$EXTEND" != 0 ] && [ -z "$RUN_IN" ]; then
    CARRIED_VOCAB=${DATA_IN:+$DATA_IN/vocab_extended_$EXTEND.npz}
    if [ -n "$CARRIED_VOCAB" ] && [ -f "$CARRIED_VOCAB" ] &&
        "$PYTHON" trajeglish_env/device_job.py extension "$CARRIED_VOCAB" "$INIT" "$EXTEND"; then
        cp "$CARRIED_VOCAB" "$WORK/vocab.npz"
        say "training on the carried $CARRIED_VOCAB (made by make device-vocab): no extending here"
    else
        "$PYTHON" -m trajeglish_env.cli tokenizer extend --json --base "$INIT" --size "$EXTEND" \
            --out "$WORK/vocab.npz" >"$WORK/vocab.json" || die "tokenizer extend --size $EXTEND failed (see $LOG)"
        say "extended $INIT's vocabulary to $EXTEND tokens"
    fi
    VOCAB_ARGS=(--vocab "$WORK/vocab.npz")
fi

# ---- noisy input tokens drawn on the GPU (NOISE_ON_DEVICE): checked against the loaders' draw first
NOISE_ARGS=()
if [ "$NOISE_ON_DEVICE" = 1 ] || { [ "$NOISE_ON_DEVICE" = auto ] && [ "$DEVICE" = cuda ]; }; then
    CHECK_CKPT=shipped
    if [ -n "${INIT:-}" ] && [ -z "$RUN_IN" ]; then CHECK_CKPT=$INIT; fi
    if timeout 180 "$PYTHON" -m trajeglish_env.training.device_noise "$CHECK_CKPT" "$DEVICE" "${HAVE[@]}" >"$WORK/noise_check.json"; then
        NOISE_ARGS=(--noise-on-device)
        say "noisy input tokens drawn on $DEVICE in training: $(cat "$WORK/noise_check.json")"
    else
        say "noisy input tokens stay with the loaders: the check on $DEVICE failed ($(cat "$WORK/noise_check.json" 2>/dev/null))"
    fi
fi

# ---- 6. train until the budget is spent
if [ -n "${TRAIN_MINUTES:-}" ]; then
    TRAIN_S=$(calc "$TRAIN_MINUTES * 60")
    [ "$(calc "($TRAIN_S > 0) ? 1 : 0")" = 1 ] || die "TRAIN_MINUTES=$TRAIN_MINUTES: expected a positive number"
else
    TRAIN_S=$(calc "$MINUTES * 60 - $SECONDS - $MARGIN_S")
fi
[ -n "${TRAIN_MINUTES:-}" ] || [ "$(calc "($TRAIN_S >= 5) ? 1 : 0")" = 1 ] || die "only $TRAIN_S s left to train after $SECONDS s of set-up and generation: raise MINUTES or lower GEN_MINUTES"
say "training for $TRAIN_S s on $DEVICE with $TRAIN_WORKERS loader processes"
VAL_ARGS=()
[ -z "$VAL_DIR" ] || VAL_ARGS=(--val-data "$VAL_DIR")
T_TRAIN=$SECONDS
# the model: a resumed run's own (its last.pt), INIT's unless PRESET is set, else PRESET's
PRESET_ARGS=()
if [ -z "$RUN_IN" ] && { [ ${#INIT_ARGS[@]} = 0 ] || [ -n "${GIVEN[PRESET]:-}" ]; }; then
    PRESET_ARGS=(--preset "$PRESET")
fi
rc=0
"$PYTHON" -m trajeglish_env.cli train --json --quiet --data "${HAVE[@]}" --out "$RUN" "${PRESET_ARGS[@]}" \
    --steps "$STEPS" --batch-size "$BATCH" --lr "$LR" --warmup "$WARMUP" --seed "$SEED" \
    --workers "$TRAIN_WORKERS" --val-every "$VAL_EVERY" --checkpoint-every "$CKPT_EVERY" \
    --minutes "$(calc "$TRAIN_S / 60")" "${FIT_ARGS[@]}" "${REPEAT_ARGS[@]}" "${CLOSED_ARGS[@]}" "${VAL_ARGS[@]}" "${RESUME[@]}" "${INIT_ARGS[@]}" "${SIGNAL_ARGS[@]}" "${VOCAB_ARGS[@]}" "${MAP_ARGS[@]}" "${NOISE_ARGS[@]}" >"$WORK/train.json" || rc=$?
[ "$rc" = 0 ] || say "train failed (exit code $rc); packing what was checkpointed"
cat "$WORK/train.json"

# ---- 7. what comes back
{
    echo "call=$CALL"
    echo "device=$DEVICE"
    echo "gpu=$GPU"
    echo "torch=$TORCH"
    echo "python=$PY_VERSION"
    echo "cores=$CORES"
    echo "gen_seed=$GEN_SEED"
    echo "train_shards=$N_TRAIN"
    echo "val_shards=$N_VAL"
    echo "gen_seconds=$GEN_TOOK"
    echo "train_seconds=$((SECONDS - T_TRAIN))"
    echo "train_workers=$TRAIN_WORKERS"
    echo "noise_on_device=${#NOISE_ARGS[@]}"
    for v in $SAVED_VARS; do echo "param.$v=${!v}"; done
} >"$WORK/call.env"
say "packing into $OUT"
"$PYTHON" trajeglish_env/device_job.py pack "$RUN" "$OUT" --facts "$WORK/call.env" \
    --train-json "$WORK/train.json" --log "$LOG" || exit 2
say "done in $SECONDS s"
exit "$rc"
