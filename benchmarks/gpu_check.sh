#!/usr/bin/env bash
# The GPU configs, run for real on one lent GPU (an H100/H200 session; never CI). Each stage is time-boxed and
# logged, so one failure does not hide the rest, in this order:
#   1. configs/finetune_tiny_base_cpu.yaml moved to the GPU (trainer.accelerator=gpu, bf16-mixed), then predict
#      with backend.device=cuda (on $EPISODES, an episodes.jsonl, if set: the hf backend decodes one episode at a
#      time, ~1 s each); its best_adapter/ is copied to OUT, to decode the 200 test episodes on the CPU as well;
#   2. configs/pretrain_tiny_vlm_cpu.yaml moved to the GPU for 100 vision-stage and 100 decoder steps: its pace
#      there (the CPU recipe's is ~0.5 and ~1.3-1.6 s a step), not a base;
#   3. configs/learned_gpu.yaml (strategy ddp, bf16-mixed, devices auto) for a capped number of steps, then
#      configs/learned_predict.yaml with device=cuda;
#   4. configs/finetune_smolvlm_256m.yaml as written (bf16, LoRA, accelerator gpu) on its full-size random-weight
#      replica (benchmarks/bench_replicas.py --gpu): seconds per step, the allocator's peak against the dry run's
#      prediction, one validation that generates a batch.
# Usage: bash benchmarks/gpu_check.sh DATA OUT [REFERENCE]
#   DATA: a naturalistic dataset folder; OUT: logs, results.json, predictions and metrics.csv files (bring them
#   back and score the predictions with `degusta evaluate`); REFERENCE: SmolVLM-256M-Instruct's tokenizer and
#   processor folder (../shared/reference-models/SmolVLM-256M-Instruct), for exact token counts.
set -u
DATA=$(realpath "$1"); OUT=$(realpath -m "$2"); REF=${3:+$(realpath "$3")}
WORK=${GPU_CHECK_WORK:-/tmp/gpu_check}
mkdir -p "$OUT" "$WORK"
export HF_HUB_OFFLINE=1 PYTHONUNBUFFERED=1 TOKENIZERS_PARALLELISM=false
PY=${PYTHON:-python3}
degusta=("$PY" -m degusta_learn.cli)  # an array, not a function: `timeout` runs programs only

stage() {  # stage NAME SECONDS COMMAND...: the command's output into OUT/NAME.log, its status and time printed
    local name=$1 limit=$2 start rc
    shift 2
    start=$(date +%s)
    echo "== $name (at most $limit s)"
    timeout "$limit" "$@" >"$OUT/$name.log" 2>&1
    rc=$?
    echo "   rc $rc after $(($(date +%s) - start)) s"
    tail -n 4 "$OUT/$name.log" | sed 's/^/   | /'
}

nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
nvidia-smi --query-gpu=timestamp,memory.used,utilization.gpu --format=csv -lms 500 >"$OUT/nvidia_smi.csv" 2>&1 &
SMI=$!
"$PY" -c 'import torch, transformers, peft, lightning; print("torch", torch.__version__, "cuda", torch.version.cuda,
"transformers", transformers.__version__, "peft", peft.__version__, "lightning", lightning.__version__)'

stage tiny_train "${T_TINY_TRAIN:-120}" "${degusta[@]}" train --config configs/finetune_tiny_base_cpu.yaml \
    --set dataset="$DATA" --set trainer.accelerator=gpu --set trainer.run_dir="$WORK/runs" \
    --set trainer.run_name=tiny_gpu --set trainer.progress_bar=false
find "$WORK/runs/tiny_gpu" -name metrics.csv -exec cp {} "$OUT/tiny_gpu_metrics.csv" \; 2>/dev/null

stage tiny_predict "${T_TINY_PREDICT:-80}" "${degusta[@]}" predict --config configs/predict_hf_base_finetuned.yaml \
    --set dataset="$DATA" --set model.adapter="$WORK/runs/tiny_gpu/best_adapter" --set backend.device=cuda \
    --set out="$OUT/tiny_gpu.jsonl" ${EPISODES:+--set episodes="$(realpath "$EPISODES")"}
cp -r "$WORK/runs/tiny_gpu/best_adapter" "$OUT/tiny_gpu_best_adapter" 2>/dev/null

stage pretrain_speed "${T_PRETRAIN:-70}" "${degusta[@]}" train --config configs/pretrain_tiny_vlm_cpu.yaml \
    --set trainer.accelerator=gpu --set trainer.max_steps=200 --set data.tower_steps=100 \
    --set data.steps_per_epoch=100 --set data.val_examples=8 --set trainer.run_dir="$WORK/runs" \
    --set trainer.run_name=pretrain_gpu --set export="$WORK/base_gpu" --set trainer.progress_bar=false
find "$WORK/runs/pretrain_gpu" -name metrics.csv -exec cp {} "$OUT/pretrain_gpu_metrics.csv" \; 2>/dev/null

stage learned_train "${T_LEARNED_TRAIN:-70}" "${degusta[@]}" train --config configs/learned_gpu.yaml \
    --set dataset="$DATA" --set trainer.run_dir="$WORK/runs" --set trainer.max_steps="${LEARNED_STEPS:-300}" \
    --set trainer.progress_bar=false
stage learned_predict "${T_LEARNED_PREDICT:-35}" "${degusta[@]}" predict --config configs/learned_predict.yaml \
    --set dataset="$DATA" --set checkpoint="$WORK/runs/learned_gpu" --set device=cuda --set out="$OUT/learned_gpu.jsonl"
find "$WORK/runs/learned_gpu" -name metrics.csv -exec cp {} "$OUT/learned_gpu_metrics.csv" \; 2>/dev/null
stage replica_256m "${T_REPLICA:-130}" "$PY" benchmarks/bench_replicas.py --gpu --steps 8 --data "$DATA" \
    --out "$WORK/repl" ${REF:+--reference "$REF"} smolvlm_256m
cp "$WORK/repl/results.json" "$OUT/replica_results.json" 2>/dev/null

kill "$SMI" 2>/dev/null
echo "== done"
