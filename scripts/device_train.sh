#!/usr/bin/env bash
# A campaign's GPU leg: continue CAMPAIGN for MINUTES of training on one CUDA GPU and write its
# resume state and any improved exported weights to OUT, to be brought back and committed.
#
#   bash scripts/device_train.sh CAMPAIGN MINUTES OUT [--device cuda|cpu] [--workers N]
#   # back home:  python tools/campaign_commit.py CAMPAIGN --from OUT
#
# Steps: (1) check that python imports torch (CUDA when --device cuda) and this package;
# (2) simulate the recipe's synthetic training data with all CPUs (scripts/campaign.py prepare);
# (3) copy agents/campaigns/CAMPAIGN to OUT/campaigns/ and resume it there for MINUTES
# (validation and the export happen after the training time; budget a few minutes for them);
# (4) OUT/campaigns/CAMPAIGN holds the new state and curve, OUT/weights the export when the
# validation improved; OUT/campaign.log the progress. The training's working folder stays in
# runs/ (not brought back). PYTHON chooses the interpreter (default: .venv/bin/python if it
# exists, else python3); CAMPAIGNS the folder of campaigns (default agents/campaigns).
set -euo pipefail
if [ $# -lt 3 ]; then
  sed -n 2,16p "$0"
  exit 2
fi
NAME=$1; MINUTES=$2; OUT=$3; shift 3
DEVICE=cuda; WORKERS=$(nproc)
while [ $# -gt 0 ]; do
  case "$1" in
    --device) DEVICE=$2; shift 2 ;;
    --workers) WORKERS=$2; shift 2 ;;
    *) echo "device_train.sh: unknown option $1" >&2; exit 2 ;;
  esac
done
cd "$(dirname "$0")/.."
if [ -z "${PYTHON:-}" ]; then
  if [ -x .venv/bin/python ]; then PYTHON=.venv/bin/python; else PYTHON=python3; fi
fi
CAMPAIGNS=${CAMPAIGNS:-agents/campaigns}
if [ ! -f "$CAMPAIGNS/$NAME/campaign.json" ]; then
  echo "device_train.sh: no campaign $CAMPAIGNS/$NAME (known: $(ls "$CAMPAIGNS" 2>/dev/null | tr '\n' ' '))" >&2
  exit 2
fi
"$PYTHON" - "$DEVICE" <<'EOF'
import sys
import torch
import envs, agents  # noqa: F401  (this package imports)
device = sys.argv[1]
if device.startswith("cuda") and not torch.cuda.is_available():
    sys.exit(f"device_train.sh: --device {device} but torch {torch.__version__} sees no CUDA GPU")
print(f"torch {torch.__version__}, device {device}" + (f" ({torch.cuda.get_device_name()})" if device.startswith("cuda") else ""))
EOF
mkdir -p "$OUT/campaigns" "$OUT/weights"
rm -rf "${OUT:?}/campaigns/$NAME"
cp -r "$CAMPAIGNS/$NAME" "$OUT/campaigns/$NAME"
"$PYTHON" scripts/campaign.py prepare "$NAME" --campaigns-dir "$OUT/campaigns" --workers "$WORKERS"
"$PYTHON" scripts/campaign.py resume "$NAME" --campaigns-dir "$OUT/campaigns" --weights-dir "$OUT/weights" \
  --runs "${RUNS:-runs/campaigns}" --minutes "$MINUTES" --device "$DEVICE" --quiet 2>&1 | tee "$OUT/campaign.log"
"$PYTHON" scripts/campaign.py status "$NAME" --campaigns-dir "$OUT/campaigns"
echo "bring it back: python tools/campaign_commit.py $NAME --from $OUT"
