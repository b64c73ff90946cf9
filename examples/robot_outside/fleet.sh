#!/usr/bin/env bash
# Two rigs drive one study side by side: each driver is its own worker, holding its own trial.
#
#   bash examples/robot_outside/fleet.sh [STUDY_DIR]       # then: ppprops show STUDY_DIR
#
# The study is created with --parallel 2: up to two trials are out at once, one per worker. Each
# driver asks with its own --worker name (the same name gets its own trial back after a crash, with
# no second LLM call), waits with --wait while both trials are out or a round waits to be told, and
# tells with its name. The LLM proposes two candidates per round from the same shown history.
# Settings: PPPROPS_METHOD (default pp), PPPROPS_WARMUP (10), PPPROPS_ITERATIONS (20); extra flags
# for `study create` after the directory.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
dir=${1:-runs/robot-fleet}
shift || true

if [ ! -e "$dir/run.sqlite" ]; then
    ppprops study create --task-file "$here/robot.toml" --method "${PPPROPS_METHOD:-pp}" --parallel 2 \
        --warmup "${PPPROPS_WARMUP:-10}" --iterations "${PPPROPS_ITERATIONS:-20}" --out "$dir" "$@"
fi

drive() {  # one rig: ask as worker $1, run the trial, tell; until nothing is left to ask
    local worker=$1 trial number status
    while true; do
        status=0
        trial=$(ppprops ask "$dir" --worker "$worker" --wait) || status=$?
        if [ "$status" -eq 3 ]; then return 0; fi        # 3: nothing more to ask
        if [ "$status" -ne 0 ]; then return "$status"; fi  # 2: an error, already printed in one line
        number=$(printf '%s\n' "$trial" | awk 'match($0, /"trial": [0-9]+/) { print substr($0, RSTART + 9, RLENGTH - 9) }')
        printf '%s\n' "$trial" | awk -f "$here/rig_arm.awk" | ppprops tell "$dir" "$number" --worker "$worker" --stdin
    done
}

drive rig-1 & first=$!
drive rig-2 & second=$!
wait "$first"
wait "$second"
ppprops study finalize "$dir"
