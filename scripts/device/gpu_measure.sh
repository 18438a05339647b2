#!/usr/bin/env bash
# One-shot GPU measurement of `ns-train moisst` (device machine: Python 3.12, torch+CUDA preinstalled, no internet).
#
# Runs in the repo root. Needs, carried with the tree: .whl/site-py312.tar.xz (scripts/device/build_bundle.sh) and,
# optionally, .devdata/k48 (KITTI raw drive 0048 as a moisst rig). Any extra .whl/*.whl are pip-installed on top.
#   bash scripts/device/gpu_measure.sh            # OUT=<folder for the results> (default outputs/gpu_measure)
# Knobs: STEPS (3000), BUDGET (seconds from start by which every training is stopped, 400; the whole script ends ~40 s later), PYTHON (python3),
# RUNS (which of "k48 with without" to run, default all);
# for a local CPU dry run only: EXTRA_ARGS (appended to every ns-train, e.g. "--machine.device-type cpu") and
# SYNTH_ARGS (appended to moisst-synth, e.g. "--frames 8 --width 64 --height 48").
#
# Three trainings run concurrently on the one GPU, each its own process, log $OUT/<name>.log:
#   with    : synthetic street rig (moisst-synth default: 320x240, 50 frames, --perturb paper --seed 0), default stages
#   without : same rig, --pipeline.lidar-first False --pipeline.camera-registration False (paper's joint schedule)
#   k48     : .devdata/k48 (if present), default stages
# Then per run: wall time, exit status, GPU max_memory_allocated, errors vs ground truth (moisst-eval; from the
# last 10 logged history rows when the run was stopped before writing calibration.json).
# $OUT gets at most 11 files: 3 logs, 3 <name>_calibration.json, 3 <name>_report.json, summaries.json, report.txt.
set -uo pipefail
T0=$(date +%s)
OUT=${OUT:-$PWD/outputs/gpu_measure}
STEPS=${STEPS:-3000}
BUDGET=${BUDGET:-400}
PY=${PYTHON:-python3}
SITE=${SITE:-/tmp/site}
RIG=${RIG:-/tmp/gpu_measure_street}
RUNS=" ${RUNS:-k48 with without} "
mkdir -p "$OUT"
export OUT PYTHONUNBUFFERED=1 PYTHONWARNINGS=ignore
log() { echo "[gpu_measure +$(($(date +%s) - T0))s] $*"; }

# --- packages -----------------------------------------------------------------------------------------------------
if [ ! -f "$SITE/MOISST_BUNDLE.txt" ]; then
    mkdir -p "$SITE"
    tar -xJf .whl/site-py312.tar.xz -C "$SITE" 2>/dev/null \
        || "$PY" -c "import sys, tarfile; tarfile.open(sys.argv[1]).extractall(sys.argv[2])" .whl/site-py312.tar.xz "$SITE" \
        || { log "FAILED: unpack .whl/site-py312.tar.xz"; exit 1; }
fi
if compgen -G ".whl/*.whl" >/dev/null; then
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" .whl/*.whl \
        || log "WARNING: pip install .whl/*.whl failed"
fi
export PYTHONPATH="$SITE:$PWD"
export NERFSTUDIO_METHOD_CONFIGS="moisst=moisst_ns.method_configs:moisst_method,moisst-lite=moisst_ns.method_configs:moisst_lite_method"
export NERFSTUDIO_DATAPARSER_CONFIGS="moisst-rig=moisst_ns.data.dataparser:moisst_rig_dataparser,moisst-kitti360=moisst_ns.data.kitti360_dataparser:moisst_kitti360_dataparser"
"$PY" -m compileall -q -j 0 "$SITE" moisst_ns >/dev/null 2>&1 || true
log "packages ready ($(wc -l < "$SITE/MOISST_BUNDLE.txt") in $SITE)"
nvidia-smi -L || log "WARNING: nvidia-smi -L failed"
"$PY" -c "
import torch, numpy, open3d, nerfstudio.scripts.train, moisst_ns.method_configs
print('python', __import__('sys').version.split()[0], 'torch', torch.__version__, 'cuda', torch.version.cuda,
      'available', torch.cuda.is_available(), 'numpy', numpy.__version__, 'open3d', open3d.__version__)
" 2>&1 | grep -v '^Info: Loading' || { log "FAILED: imports"; exit 1; }
nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader,nounits -l 5 > /tmp/gpu_measure_smi.csv 2>/dev/null &
SMI=$!

# --- trainings ----------------------------------------------------------------------------------------------------
NAMES=()
train() {  # NAME DATA [ns-train options...]: background; status in /tmp/gpu_measure_NAME.status
    local name=$1 data=$2 left t
    shift 2
    left=$((BUDGET - ($(date +%s) - T0)))
    rm -rf "outputs/$name" "/tmp/gpu_measure_$name.status"
    NAMES+=("$name")
    log "start $name (timeout ${left}s): ns-train moisst --data $data $*"
    (
        t=$(date +%s)
        timeout -k 15 "$left" "$PY" scripts/device/ns_train_mem.py moisst --data "$data" --max-num-iterations "$STEPS" \
            --vis tensorboard --machine.seed 0 --output-dir outputs --experiment-name "$name" --timestamp run "$@" ${EXTRA_ARGS:-} \
            > "$OUT/$name.log" 2>&1
        echo "$? $(($(date +%s) - t))" > "/tmp/gpu_measure_$name.status"
    ) &
}

if [[ $RUNS == *" k48 "* ]]; then
    if [ -d .devdata/k48 ]; then train k48 .devdata/k48; else log "no .devdata/k48: KITTI run skipped"; fi
fi
if [[ $RUNS == *" with "* || $RUNS == *" without "* ]]; then
    rm -rf "$RIG"
    log "moisst-synth street rig -> $RIG"
    if "$PY" -m moisst_ns.cli.synth "$RIG" --perturb paper --seed 0 --width 320 --height 240 ${SYNTH_ARGS:-} 2>&1 | tail -n 2; then
        [[ $RUNS == *" with "* ]] && train with "$RIG"
        [[ $RUNS == *" without "* ]] && train without "$RIG" --pipeline.lidar-first False --pipeline.camera-registration False
    else
        log "FAILED: moisst-synth"
    fi
fi
[ "${#NAMES[@]}" -gt 0 ] || { log "nothing to run"; exit 1; }

while :; do
    running=0
    for n in "${NAMES[@]}"; do [ -f "/tmp/gpu_measure_$n.status" ] || running=$((running + 1)); done
    [ "$running" -eq 0 ] && break
    sleep 20
    for n in "${NAMES[@]}"; do
        [ -f "/tmp/gpu_measure_$n.status" ] && continue
        echo "  $n: $(tr '\r' '\n' < "$OUT/$n.log" | sed 's/\x1b\[[0-9;]*[A-Za-z]//g' | grep -v '^\s*$' | tail -n 1 | cut -c1-150)"
    done
    log "$running running; GPU util,mem(MiB): $(tail -n 1 /tmp/gpu_measure_smi.csv 2>/dev/null)"
done
kill "$SMI" 2>/dev/null

# --- report -------------------------------------------------------------------------------------------------------
{
    echo "=== gpu_measure: STEPS=$STEPS, budget ${BUDGET}s, $(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -n 1)"
    awk -F', ' '{u+=$1; if ($1>mu) mu=$1; if ($2>mm) mm=$2; n++} END {if (n) printf "GPU over the run: mean util %.0f %%, max util %d %%, max memory.used %d MiB (all processes)\n", u/n, mu, mm}' /tmp/gpu_measure_smi.csv
    for n in "${NAMES[@]}"; do
        read -r rc wall < "/tmp/gpu_measure_$n.status"
        run=outputs/$n/moisst/run
        case $n in k48) gt=.devdata/k48/ground_truth.json ;; *) gt=$RIG/ground_truth.json ;; esac
        echo
        echo "=== $n: exit $rc, wall ${wall}s$([ "$rc" = 124 ] && echo ' (STOPPED BY TIMEOUT)')"
        grep -h '^\[gpu_measure\]' "$OUT/$n.log" | sed 's/^/  /'
        grep -hE '^wrote .*calibration.json' "$OUT/$n.log" | sed 's/^/  /'
        if [ -f "$run/report/report.json" ]; then
            cp "$run/report/report.json" "$OUT/${n}_report.json"
            "$PY" -c "import json,sys; [print(f\"  scene check {r['camera']}: median |rendered depth - LiDAR depth| {r['median_depth_residual_m']:.3f} m over {r['points']} points\") for r in json.load(open(sys.argv[1]))['renders']]" "$run/report/report.json"
        fi
        if [ -f "$run/calibration.json" ]; then
            cp "$run/calibration.json" "$OUT/${n}_calibration.json"
            echo "  errors of calibration.json vs $gt:"
            "$PY" -m moisst_ns.cli.evaluate "$run/calibration.json" "$gt" 2>&1 | sed 's/^/    /'
        elif [ -f "$run/calibration_history.csv" ]; then
            echo "  no calibration.json; last 10 logged estimates (calibration_history.csv):"
            "$PY" -m moisst_ns.cli.evaluate --history "$run" --last 10 --columns errors 2>&1 | sed 's/^/    /'
        fi
        if [ "$rc" != 0 ]; then
            echo "  last lines of $n.log:"
            tr '\r' '\n' < "$OUT/$n.log" | sed 's/\x1b\[[0-9;]*[A-Za-z]//g' | grep -v '^\s*$' | tail -n 25 | cut -c1-200 | sed 's/^/    /'
        fi
    done
    echo
    "$PY" - "${NAMES[@]}" <<'EOF'
import json, sys
from pathlib import Path
out, summaries = Path(__import__("os").environ["OUT"]), {}
for name in sys.argv[1:]:
    p = Path("outputs") / name / "moisst" / "run" / "summary.json"
    if p.is_file():
        summaries[name] = s = json.loads(p.read_text())
        lf = {k: round(v.get("wall_s", 0), 1) for k, v in (s.get("lidar_first") or {}).items() if isinstance(v, dict)}
        cr = {k: round(v.get("wall_s", 0), 1) for k, v in (s.get("camera_registration") or {}).items() if isinstance(v, dict)}
        print(f"{name}: summary wall_time_s {s.get('wall_time_s', float('nan')):.1f}, iterations {s.get('iterations')}, "
              f"lidar_first wall_s {lf}, camera_registration wall_s {cr}")
        for key in ("errors_before", "errors_after", "errors_final"):
            for sensor, e in (s.get(key) or {}).items():
                print(f"  {key:13s} {sensor:16s} {e['translation_cm']:8.2f} cm {e['rotation_deg']:7.3f} deg {e['time_ms']:8.2f} ms")
        for sensor, v in (s.get("verdicts") or {}).items():
            if isinstance(v, dict):
                print(f"  verdict {sensor:16s} {v.get('verdict')}: {str(v.get('reason', ''))[:110]}")
(out / "summaries.json").write_text(json.dumps(summaries, indent=1))
EOF
    echo "=== total wall $(($(date +%s) - T0))s"
} 2>&1 | tee "$OUT/report.txt"
for n in "${NAMES[@]}"; do  # keep the logs small enough to come back
    [ "$(stat -c %s "$OUT/$n.log")" -gt 3000000 ] && { tail -c 3000000 "$OUT/$n.log" > "$OUT/$n.log.t" && mv "$OUT/$n.log.t" "$OUT/$n.log"; }
done
ls -la "$OUT"
