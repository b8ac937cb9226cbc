#!/usr/bin/env bash
# Ship a training run's best checkpoint as the shipped model NAME (`default`, or another name that
# `spk2img reconstruct/serve --model NAME` then runs): keep the model it replaces for the bench
# (spk2img/assets/models/previous/<member>.pt for `default`, previous/<NAME>-<member>.pt for the
# others; then `spk2img bench --trained previous=...`), strip the optimiser state, export and
# verify the ONNX graph with its block graphs, write the model card (docs/model_card.md for
# `default`, else docs/model_card_NAME.md; the README figure too for `default`) and keep the run's
# metrics log in training_state/, gzip-compressed (its last.pt only by hand, for the one run in
# progress).
# Usage: scripts/ship_model.sh NAME runs/RUN [--chosen-on SET] [MODEL-CARD OPTIONS, e.g.
#        --data DIR --real-capture CAPTURE.npz --history "..."]
# --chosen-on records what best.pt was chosen on when that was done after the run (e.g. "real
# video frames": a step picked on the whole-frame real-video validation and copied to best.pt);
# the model card then says so. Without it, the run's own record stands.
set -euo pipefail
usage="usage: $0 NAME RUN_DIR [--chosen-on SET] [MODEL-CARD OPTIONS]"
name=${1:?$usage}
run=${2:?$usage}
shift 2
chosen=""
if [ "${1:-}" = --chosen-on ]; then
  chosen=${2:?$usage}
  python -c "import sys; from spk2img.training.train import SELECTIONS as s; sys.argv[1] in s or \
sys.exit(f'ship_model.sh: --chosen-on {sys.argv[1]!r} is none of {\", \".join(s)}')" "$chosen"
  shift 2
fi
models=spk2img/assets/models
model=$models/spk2img-$name
state=training_state/$(basename "$run")
if [ "$name" = default ]; then card=docs/model_card.md; kept=""; else card=docs/model_card_$name.md; kept="$name-"; fi
mkdir -p "$models" "$models/previous" "$state" docs
if [ -f "$model.pt" ]; then
  member=$(python -c "from spk2img.model.checkpoint import load_checkpoint as l; print(l('$model.pt')['member'])")
  cp "$model.pt" "$models/previous/$kept$member.pt"
fi
python -c "import sys; from spk2img.model.checkpoint import release_checkpoint as r
r(sys.argv[1], sys.argv[2], val_set=sys.argv[3] or None)" "$run/best.pt" "$model.pt" "$chosen"
spk2img export "$model.pt" --out "$model.onnx" --name "spk2img-$name" --deform-conv
spk2img verify "$model.onnx" --json "docs/verify_$name.json" | tee "docs/verify_$name.txt"
# the run's whole log replaces any compressed one an earlier ship of the same run left
rm -f "$state/metrics.jsonl.gz"
cp "$run/metrics.jsonl" "$state/"
python -m spk2img.training.model_card --checkpoint "$model.pt" --onnx "$model.onnx" \
    --run-dir "$state" --out "$card" "$@"
if [ "$name" = default ]; then python scripts/readme_figure.py; fi
# the finished run's log, compressed (training_state/README.md; the campaign report reads both)
gzip -9 -n -f "$state/metrics.jsonl"
