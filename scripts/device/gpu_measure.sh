#!/usr/bin/env bash
# `ns-train moisst` (paper settings) on a GPU machine of the `device` tool (issue 36), with and without the stages.
#
#   bash scripts/device/gpu_measure.sh RIG STAGES OUT SECONDS [RUNS]
#
# RIG: a moisst-rig/1 folder; STAGES: a moisst-calibrate OUT (or ns-train run folder) of that rig whose lidar_first/
# and camera_registration/ the "stages" run loads (--pipeline.stages-from: the stages ran on the CPU machine, where
# their wall time is measured); OUT: each run's log, summary.json and report.json; SECONDS: this script's budget.
# RUNS: "stages nostages" (default), in that order; "nostages" is --pipeline.lidar-first False
# --pipeline.camera-registration False (the paper's joint schedule from the priors). The first run is FIRST_STEPS
# (1000) steps and gives the step rate (its summary's wall over its steps); the next is as long as the budget leaves
# (at least MIN_STEPS, 300; at most the preset's 30000; the schedules rescale to the run's length).
#
# The machine has python3 (3.12) with torch (CUDA), numpy 2, scipy, opencv, matplotlib, scikit-image, tensorboard,
# torchmetrics; the rest travels as the wheels of scripts/device/fetch_wheels.sh in .whl/ (carry .whl and the rig),
# installed into /tmp/site once per machine. open3d does not travel: scripts/device/open3d_standin stands in for the
# one call of an `ns-train moisst --pipeline.stages-from` run (the LiDAR map's voxel_down_sample; the same points).
# Peak GPU memory: nvidia-smi's memory.used (every process, the CUDA context included), sampled every 0.5 s.
set -uo pipefail
RIG=$1 STAGES=$2 OUT=$3 BUDGET=$4 RUNS=${5:-"stages nostages"}
START=$(date +%s)
export PYTHONUNBUFFERED=1
if [ ! -f /tmp/site/.done ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl && touch /tmp/site/.done || exit 1
fi
export PYTHONPATH=/tmp/site:$PWD:$PWD/scripts/device/open3d_standin
export NERFSTUDIO_METHOD_CONFIGS=moisst=moisst_ns.method_configs:moisst_method
export NERFSTUDIO_DATAPARSER_CONFIGS=moisst-rig=moisst_ns.data.dataparser:moisst_rig_dataparser
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
python3 -c "import sys, torch, numpy; print(sys.version.split()[0], torch.__version__, torch.cuda.get_device_name(0), 'numpy', numpy.__version__)"
mkdir -p "$OUT" "${RUN_DIR:-/tmp/moisst_runs}"
rate=""
for run in $RUNS; do
    left=$(( BUDGET - ($(date +%s) - START) ))
    if [ -z "$rate" ]; then steps=${FIRST_STEPS:-1000}; else steps=$(python3 -c "print(max(${MIN_STEPS:-300}, min(30000, int(($left - 100) / $rate) // 100 * 100)))"); fi
    [ "$left" -lt 150 ] && { echo "$run: skipped, ${left} s left"; continue; }
    case $run in
        nostages) extra=(--pipeline.lidar-first False --pipeline.camera-registration False) ;;
        stages) extra=(--pipeline.stages-from "$STAGES") ;;
        *) echo "unknown run $run"; exit 2 ;;
    esac
    echo "== $run: $steps steps, ${left} s left"
    t0=$(date +%s)
    nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -lms 500 > "${RUN_DIR:-/tmp/moisst_runs}/mem_$run" & sampler=$!
    python3 -m nerfstudio.scripts.train moisst --data "$RIG" --max-num-iterations "$steps" --machine.seed 42 --vis tensorboard \
        --viewer.quit-on-train-completion True --output-dir "${RUN_DIR:-/tmp/moisst_runs}/$run" "${extra[@]}" > "$OUT/$run.log" 2>&1
    rc=$?
    wall=$(( $(date +%s) - t0 ))
    kill $sampler 2>/dev/null
    echo "$run: peak GPU memory $(sort -n "${RUN_DIR:-/tmp/moisst_runs}/mem_$run" | tail -1) MiB"
    summary=$(find "${RUN_DIR:-/tmp/moisst_runs}/$run" -name summary.json | head -1)
    echo "$run: exit $rc, ${wall} s wall"
    sed -n '/^errors of the priors/,/^Printing profiling/p' "$OUT/$run.log" | cut -c1-400
    grep -E "Traceback|Error" -A3 "$OUT/$run.log" | tail -20
    if [ -n "$summary" ]; then
        cp "$summary" "$OUT/$run.summary.json"
        cp "$(dirname "$summary")/report/report.json" "$OUT/$run.report.json" 2>/dev/null
        rate=$(python3 -c "import json; s = json.load(open('$summary')); print(s['wall_time_s'] / s['iterations'])")
        echo "$run: $(python3 -c "import json; s = json.load(open('$summary')); print(s['iterations'], 'steps', round(s['wall_time_s'], 1), 's trained')") -> $rate s/step"
    fi
done
python3 - "$OUT" <<'EOF'
import json, sys, pathlib
for f in sorted(pathlib.Path(sys.argv[1]).glob("*.summary.json")):
    s = json.loads(f.read_text())
    print(f.name, json.dumps({k: s.get(k) for k in ("iterations", "wall_time_s", "errors_final", "verdicts")}, default=str)[:3000])
EOF
