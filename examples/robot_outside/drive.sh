#!/usr/bin/env bash
# A robot outside Python drives a PP-ProPS search with `ppprops ask` and `ppprops tell` only.
#
#   bash examples/robot_outside/drive.sh [STUDY_DIR]       # then: ppprops show STUDY_DIR
#
# Any program that can run a command and read one line of JSON can do the same: the rig's driver
# here is an awk script (rig_arm.awk) that never imports ppprops. The loop survives a crash or a
# reboot: run the script again and it continues where the study stands (a trial asked and not told
# is asked again, without a second LLM call). Settings: PPPROPS_METHOD (default pp),
# PPPROPS_WARMUP (10), PPPROPS_ITERATIONS (20); extra flags for `study create` after the directory.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
dir=${1:-runs/robot-outside}
shift || true

if [ ! -e "$dir/run.sqlite" ]; then
    ppprops study create --task-file "$here/robot.toml" --method "${PPPROPS_METHOD:-pp}" \
        --warmup "${PPPROPS_WARMUP:-10}" --iterations "${PPPROPS_ITERATIONS:-20}" --out "$dir" "$@"
fi

while true; do
    status=0
    trial=$(ppprops ask "$dir") || status=$?
    if [ "$status" -eq 3 ]; then break; fi           # 3: nothing more to ask
    if [ "$status" -ne 0 ]; then exit "$status"; fi  # 2: an error, already printed in one line
    number=$(printf '%s\n' "$trial" | awk 'match($0, /"trial": [0-9]+/) { print substr($0, RSTART + 9, RLENGTH - 9) }')
    printf '%s\n' "$trial" | awk -f "$here/rig_arm.awk" | ppprops tell "$dir" "$number" --stdin
done

# The rig's own final trials of the best policy would be told here with --return; without them the
# study records the best policy and writes best_policy.json (the rig deploys W and b from it).
ppprops study finalize "$dir"
