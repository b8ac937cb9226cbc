#!/usr/bin/env bash
# Ship a training run's best checkpoint as the default model: keep the default it replaces for the
# bench (spk2img/assets/models/previous/<member>.pt, then `spk2img bench --trained
# previous=...`), strip the optimiser state, export and verify the ONNX graph, write the model
# card and the README figure, and keep the run's resumable state (last.pt + metrics log) in
# training_state/ so a later session can continue it.
# Usage: scripts/ship_default_model.sh runs/lite-v1 [MODEL-CARD OPTIONS, e.g. --data DIR
#        --real-capture CAPTURE.npz --history "..."]
set -euo pipefail
run=${1:?usage: $0 RUN_DIR [MODEL-CARD OPTIONS]}
shift
models=spk2img/assets/models
state=training_state/$(basename "$run")
mkdir -p "$models" "$models/previous" "$state" docs
if [ -f "$models/spk2img-default.pt" ]; then
  member=$(python -c "from spk2img.model.checkpoint import load_checkpoint as l; print(l('$models/spk2img-default.pt')['member'])")
  cp "$models/spk2img-default.pt" "$models/previous/$member.pt"
fi
python -c "from spk2img.model.checkpoint import release_checkpoint as r; r('$run/best.pt', '$models/spk2img-default.pt')"
spk2img export "$models/spk2img-default.pt" --out "$models/spk2img-default.onnx" --name spk2img-default --deform-conv
spk2img verify "$models/spk2img-default.onnx" --json docs/verify_default.json | tee docs/verify_default.txt
cp "$run/last.pt" "$run/metrics.jsonl" "$state/"
python -m spk2img.training.model_card --checkpoint "$models/spk2img-default.pt" \
    --onnx "$models/spk2img-default.onnx" --run-dir "$state" "$@"
python scripts/readme_figure.py
