#!/usr/bin/env bash
# The prepared GPU check: one command on a machine with a CUDA GPU, under 8 minutes on one GPU.
#
#   bash scripts/device_check.sh [OUT]             # default OUT: runs/device-check
#   bash scripts/device_check.sh OUT --dry-run     # every step on the CPU at the smallest sizes:
#                                                  # checks this script on a machine without a GPU
#
# Steps (each timed; a failed step is reported and the next one still runs):
#   1. environment: torch sees CUDA; GPU, torch, CUDA and cuDNN versions, bf16 support
#   2. tests/test_cuda.py: every network forward/backward, the losses, two training steps
#      (float32, bf16, fp16), evaluate and predict with --device cuda, all against the CPU;
#      the 2-process NCCL stop-and-resume test where there are 2 GPUs (skipped on one)
#   3. a short training run with --device cuda --amp bf16 (synthetic-mini, validation on), stopped
#      at step 20 and resumed to step 30: every step logged once
#   4. an evaluation of that checkpoint with --device cuda (and zero flow beside it)
#   5. training throughput (windows/s) of EV-MGRFlowNet at CPU and paper width, float32 and bf16
#      (scripts/benchmark.py --only training precision --device cuda)
# Everything is also written to OUT/device_check.log, with a summary at its end to paste into
# docs/training.md ("What has run on a GPU"). Needs the project installed with a CUDA build of
# torch (pip install -e ".[test]"). PYTHON chooses the interpreter (default: .venv/bin/python
# if it exists, else python3).
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=runs/device-check; DEVICE=cuda; BENCH=()
for arg in "$@"; do
  case "$arg" in
    --dry-run) DEVICE=cpu; BENCH=(--tiny --threads 1) ;;
    -*) echo "device_check.sh: unknown option $arg" >&2; exit 2 ;;
    *) OUT=$arg ;;
  esac
done
if [ -z "${PYTHON:-}" ]; then
  if [ -x .venv/bin/python ]; then PYTHON=.venv/bin/python; else PYTHON=python3; fi
fi
mkdir -p "$OUT"
LOG="$OUT/device_check.log"
: > "$LOG"
exec > >(tee -a "$LOG") 2>&1
SUMMARY=()
FAILED=0
START=$(date +%s)

step() {  # step NAME COMMAND...: run, time, record
  local name=$1; shift
  echo; echo "=== $name: $*"
  local t0=$(date +%s)
  "$@"
  local rc=$? t=$(( $(date +%s) - t0 ))
  if [ $rc -eq 0 ]; then SUMMARY+=("ok     ${t}s  $name"); else SUMMARY+=("FAILED ${t}s  $name (exit $rc)"); FAILED=1; fi
  return 0
}

echo "device_check.sh $(date -u +%Y-%m-%dT%H:%M:%SZ) on $(hostname), commit $(git rev-parse --short HEAD 2>/dev/null || echo '?')"
step "environment" "$PYTHON" - "$DEVICE" <<'EOF'
import sys
import torch
import agents, envs, losses  # noqa: F401  (the project imports)
if sys.argv[1] == "cpu":
    sys.exit(print(f"dry run on the CPU: torch {torch.__version__}, {torch.get_num_threads()} threads"))
if not torch.cuda.is_available():
    sys.exit(f"torch {torch.__version__} (CUDA build {torch.version.cuda}) sees no CUDA device")
device = torch.device("cuda")
props = torch.cuda.get_device_properties(device)
print(f"torch {torch.__version__}, CUDA {torch.version.cuda}, cuDNN {torch.backends.cudnn.version()}, "
      f"NCCL {'.'.join(map(str, torch.cuda.nccl.version())) if torch.distributed.is_nccl_available() else 'none'}")
print(f"{torch.cuda.device_count()} GPU(s); 0: {props.name}, {props.total_memory / 2**30:.0f} GiB, "
      f"compute capability {props.major}.{props.minor}, bf16 {'yes' if torch.cuda.is_bf16_supported() else 'no'}")
EOF
if [ "$FAILED" -ne 0 ]; then
  echo "device_check.sh: no usable CUDA device; nothing else to check" >&2
  exit 1
fi

step "tests/test_cuda.py" env OMP_NUM_THREADS=4 "$PYTHON" -m pytest -q -ra tests/test_cuda.py

RUN="$OUT/train-bf16"
rm -rf "$RUN" "$OUT/eval"
TRAIN=(--data synthetic-mini --num-envs 4 --unroll 4 --val-data synthetic-mini --val-windows 4 --val-every 10
       --no-progress --device "$DEVICE")
step "train 20 steps ($DEVICE, bf16)" "$PYTHON" scripts/train.py "${TRAIN[@]}" --amp bf16 --steps 20 --ckpt-every 10 \
  --out "$RUN"
step "resume to 30 steps" "$PYTHON" scripts/train.py --resume --steps 30 --out "$RUN" --val-data synthetic-mini \
  --val-windows 4 --val-every 10 --no-progress --device "$DEVICE"
step "every step logged once, bf16 kept" "$PYTHON" - "$RUN" <<'EOF'
import json, sys
from pathlib import Path
from agents.checkpoint import load_checkpoint
run = Path(sys.argv[1])
rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
steps = [r["step"] for r in rows if "loss" in r]
assert steps == list(range(1, 31)), steps
payload = load_checkpoint(run / "checkpoint.pt")
assert payload["step"] == 30 and payload["config"]["amp"] == "bf16", (payload["step"], payload["config"]["amp"])
print(f"steps 1-30 once each; loss {rows[0]['loss']:.4f} -> {[r for r in rows if 'loss' in r][-1]['loss']:.4f}; "
      f"{[r for r in rows if 'loss' in r][-1]['windows_per_s']:.1f} windows/s; "
      + " ".join(f"{k}={v:.4f}" for k, v in rows[-1].items() if k.startswith("val_")))
EOF
step "evaluate ($DEVICE)" "$PYTHON" scripts/evaluate.py --checkpoint "$RUN/checkpoint.pt" --zero --data synthetic-mini \
  --dt 1 --pictures 0 --no-progress --device "$DEVICE" --out "$OUT/eval"
step "throughput ($DEVICE)" "$PYTHON" scripts/benchmark.py --only training precision --device "$DEVICE" ${BENCH[@]+"${BENCH[@]}"}

echo
echo "=== summary ($(( $(date +%s) - START )) s in all; log: $LOG)"
printf '%s\n' "${SUMMARY[@]}"
grep -E "^training +\|" "$LOG" | sed 's/^/  /'
grep -E "^precision +\|.*median" "$LOG" | sed 's/^/  /'
exit $FAILED
