#!/usr/bin/env bash
# The one-shot training run on a rented GPU machine, from a folder scripts/device-pack.sh made:
# unpack; check that the device computes what the CPU does (the run stops there if not); time
# the PyTorch reference on the same chip; train from the packed weights for what is left of the
# budget; export sharded weights; and leave in OUT at most 8 files:
#   OUT/model/config.json, OUT/model/model*.safetensors[.index.json]   the exported weights
#   OUT/summary.txt    what the run measured (also printed)
#   OUT/logs.tar.gz    train.log, log.jsonl, check.json, torch.jsonl, gpu.csv, nvidia-smi.txt
# Runs on the CPU too (DEVICE=cpu), as the test does with a tiny budget.
#
# Usage: scripts/device-run.sh BUNDLE OUT
# Environment:
#   DEVICE             cuda:0 (default) or cpu
#   BUDGET             seconds for the whole script (default 480); training gets what the
#                      steps before it leave, less EXPORT_RESERVE (default 30)
#   BATCH_FACES        face positions per step (default 65536)
#   STEPS              the learning-rate schedule's length (default 2000)
#   TF32               1 (default): f32 matrix products on TF32 tensor cores, checked against
#                      the CPU at a 1e-2 tolerance first; 0: plain f32
#   REFERENCE_SECONDS  timed seconds per PyTorch setting, f32 and bf16 (default 20; 0: none)
#   CHECK_MESHES       held-aside shapes the device check runs (default 8)
#   BENCH_POSITIONS    batch sizes `meshstream-train bench --ops` times phase by phase and
#                      block by block before training (default 16384,65536; empty: none)
#   TRAIN_ARGS         more `meshstream-train ae` options
set -uo pipefail
bundle=$(realpath "${1:?usage: device-run.sh BUNDLE OUT}")
out=$(realpath -m "${2:?usage: device-run.sh BUNDLE OUT}")
device=${DEVICE:-cuda:0}
budget=${BUDGET:-480}
export_reserve=${EXPORT_RESERVE:-30}
batch_faces=${BATCH_FACES:-65536}
steps=${STEPS:-2000}
reference_seconds=${REFERENCE_SECONDS:-20}
tf32=${TF32:-1}
check_meshes=${CHECK_MESHES:-8}
bench_positions=${BENCH_POSITIONS-16384,65536}
started=$(date +%s)
work=$(mktemp -d)
logs=$work/logs
mkdir -p "$out" "$logs"
summary=$out/summary.txt
: >"$summary"

say() { echo "$*" | tee -a "$summary"; }
# Packs the logs and ends the script: whatever happened, what was measured comes back.
finish() {
    tar -C "$logs" -czf "$out/logs.tar.gz" .
    say "device-run: $1 after $(($(date +%s) - started)) s"
    rm -rf "$work"
    exit "${2:-0}"
}

# Unpack.
xz -dc "$bundle/meshstream-train.xz" >"$work/meshstream-train" && chmod +x "$work/meshstream-train" \
    || finish "the trainer did not unpack" 1
mkdir -p "$work/data"
cp "$bundle/data/manifest.csv" "$work/data/"
xz -dc "$bundle/data/meshes.tar.xz" | tar -C "$work/data" -xf - || finish "the meshes did not unpack" 1
train=$work/meshstream-train
# The packed weights to start from; without them the run starts from scratch, and the device
# check uses the shipped model.
init=$bundle/init
check_model=$init
[[ -d $init ]] || check_model=models/default

if [[ $device == cuda* ]]; then
    # No toolkit there: the driver brings libcuda.so.1, PyTorch's wheels the CUDA libraries.
    for lib in libcudart.so.13 libcublas.so.13 libcurand.so.10; do
        found=$(find / -xdev -name "$lib" -path '*nvidia*' 2>/dev/null | head -1)
        [[ -n $found ]] && LD_LIBRARY_PATH=$(dirname "$found")${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
    done
    export LD_LIBRARY_PATH
    nvidia-smi >"$logs/nvidia-smi.txt" 2>&1
    say "gpu: $(nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>&1)"
fi
if ldd "$train" | grep 'not found' | tee -a "$summary"; then
    finish "the trainer lacks the libraries above" 1
fi

# Does the device compute what the CPU does? Nothing is trained on it otherwise.
if ! "$train" check-device --model "$check_model" --device "$device" --meshes "$check_meshes" --json >"$logs/check.json" 2>"$logs/check.err"; then
    cat "$logs/check.err" | tee -a "$summary"
    finish "the device check failed" 1
fi
say "check: $(cat "$logs/check.json")"
if [[ $tf32 == 1 ]]; then
    "$train" check-device --model "$check_model" --device "$device" --meshes "$check_meshes" --json --tf32 --tolerance 1e-2 \
        >"$logs/check-tf32.json" 2>>"$logs/check.err" || finish "the TF32 check failed" 1
    say "check with tf32: $(cat "$logs/check-tf32.json")"
fi

# Where a step's time goes, phase by phase and block by block (forward and backward), before
# training (none with BENCH_POSITIONS=).
if [[ -n $bench_positions ]]; then
    bench_args=(--model "$check_model" --device "$device" --positions "$bench_positions" --steps 2 --ops)
    [[ $tf32 == 1 ]] && bench_args+=(--tf32)
    "$train" bench "${bench_args[@]}" >"$logs/bench.txt" 2>&1
    tee -a "$summary" <"$logs/bench.txt"
fi

# PyTorch on the same chip, same architecture and batch, for the ratio.
if [[ -f $bundle/torch_reference.py && $reference_seconds != 0 ]] && python3 -c 'import torch' 2>/dev/null; then
    torch_device=$([[ $device == cuda* ]] && echo cuda || echo cpu)
    for dtype in f32 bf16; do
        timeout $((reference_seconds * 3 + 60)) python3 "$bundle/torch_reference.py" \
            --config "$check_model/config.json" --positions "$batch_faces" --seconds "$reference_seconds" \
            --dtype "$dtype" --device "$torch_device" >>"$logs/torch.jsonl" 2>>"$logs/torch.err"
    done
    say "pytorch: $(tr '\n' ' ' <"$logs/torch.jsonl")"
fi

# Train for what is left of the budget, sampling the GPU's utilization meanwhile.
left=$((budget - ($(date +%s) - started) - export_reserve))
((left > 10)) || finish "no time left to train ($left s)" 1
sampler=
if [[ $device == cuda* ]]; then
    nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv,noheader,nounits \
        -l 1 >"$logs/gpu.csv" 2>/dev/null &
    sampler=$!
fi
init_args=()
if [[ -d $init ]]; then
    # Warm-started (the run keeps the weights' face limit and point drawing): every mesh size
    # from the first step, and a short warm-up for the fresh optimizer.
    max_faces=$(python3 -c 'import json, sys; print(json.load(open(sys.argv[1]))["max_faces"])' "$init/config.json")
    init_args=(--init "$init" --curriculum "0:$max_faces" --warmup 50)
fi
[[ $tf32 == 1 ]] && init_args+=(--tf32)
# shellcheck disable=SC2086 # TRAIN_ARGS is a list of options
"$train" ae --out "$work/run" --data "$work/data" --device "$device" --no-progress \
    --time-budget "$left" --batch-faces "$batch_faces" --steps "$steps" \
    "${init_args[@]}" ${TRAIN_ARGS:-} >"$logs/train.log" 2>&1
status=$?
[[ -n $sampler ]] && kill "$sampler" 2>/dev/null
cp "$work/run/log.jsonl" "$logs/" 2>/dev/null
tail -3 "$logs/train.log" | tee -a "$summary"
((status == 0)) || say "training exited with status $status; exporting its last checkpoint"

# Sharded weights, each shard under the 16 MiB that comes back per file.
if ! "$train" export "$work/run" -o "$out/model" --max-shard-size 15MiB >>"$logs/train.log" 2>&1; then
    finish "the export failed" 1
fi
python3 - "$logs" >>"$summary" <<'EOF'
import json, os, statistics, sys
logs = sys.argv[1]
steps = [r for r in map(json.loads, open(os.path.join(logs, "log.jsonl"))) if r["kind"] == "step"]
later = steps[len(steps) // 5:] or steps  # the first steps warm caches and kernels
if later:
    print(f"steps: {len(steps)}, face positions {sum(r['positions'] for r in steps)}, "
          f"faces/s median {statistics.median(r['faces_per_s'] for r in later):.0f}, "
          f"loss {steps[0]['coord_loss']:.3f} -> {steps[-1]['coord_loss']:.3f}")
    timing = [r.get("timing", {}) for r in later]
    total = sum(r["positions"] / r["faces_per_s"] for r in later)
    print(f"step time {total:.1f} s over {len(later)} steps: " + ", ".join(
        f"{phase} {sum(t.get(phase + '_s', 0) for t in timing):.1f} s"
        for phase in ("data_wait", "compute", "update", "average"))
        + f"; {statistics.mean(t.get('groups', 0) for t in timing):.1f} passes per step")
# The export is the best evaluation's weights (from --init, the weights it started from
# unless a step beat them).
evals = [r for r in map(json.loads, open(os.path.join(logs, "log.jsonl")))
         if r["kind"] == "eval" and r.get("chamfer_mean") is not None]
if evals:
    def figures(r):
        share = (r.get("topology") or {}).get("boundary_share_mean")
        return f"{r['chamfer_mean']:.4f}" + ("" if share is None else f" ({share:.1%} open edges)")
    print("evaluation CD by step: " + ", ".join(f"{r['step']}: {figures(r)}" for r in evals))
    best = min(evals, key=lambda r: r["chamfer_mean"])
    print(f"exported: the weights of step {best['step']} (CD {best['chamfer_mean']:.4f})")
gpu = os.path.join(logs, "gpu.csv")
if os.path.exists(gpu):
    util = [float(l.split(",")[1]) for l in open(gpu) if l.count(",") == 2]
    if util:
        print(f"gpu utilization: mean {statistics.mean(util):.0f}% over {len(util)} samples, "
              f"median {statistics.median(util):.0f}%")
EOF
cat "$summary"
finish "done" "$status"
