#!/usr/bin/env bash
# The commands of a lent GPU session (docs/gpu.md, "A GPU session"), each under 10 minutes,
# each writing its figures under $OUT (the folder that comes back). Run from the checkout:
#   scripts/gpu_session.sh torch                 # env, torch inference rows, GPU training speed
#   scripts/gpu_session.sh receive MANIFEST DEST # one part of a split file (receive_parts.sh)
#   scripts/gpu_session.sh onnx                  # onnxruntime-gpu rows (after receiving its wheel)
#   scripts/gpu_session.sh train SECONDS ARGS…   # spk2img train on cuda for at most SECONDS
#   scripts/gpu_session.sh train-start NAME SECONDS ARGS…
#                                 # the same in the background (its own process session, so it
#                                 # outlives the command): the run trains in /tmp/spk2img-runs/NAME
#                                 # while later commands send files
#   scripts/gpu_session.sh train-stop NAME
#                                 # Ctrl-C to it (it saves last.pt at its step), then its log,
#                                 # last.pt and best.pt into $OUT/NAME
set -euo pipefail
out=${OUT:-/tmp/spk2img-out}
mkdir -p "$out"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
ort=/tmp/spk2img-ort-gpu   # where receive installs the onnxruntime-gpu wheel
runs=${SPK2IMG_RUNS:-/tmp/spk2img-runs}   # where train-start trains
step=${1:?torch, receive, onnx, train, train-start or train-stop}
shift
case "$step" in
  torch)
    { python3 --version; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
      python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)"
    } > "$out/environment.txt" 2>&1
    cat "$out/environment.txt"
    timeout 240 python3 scripts/torch_inference_speed.py --device cuda --compile \
      --json "$out/torch_inference.json" || echo "torch inference rows: exit $?"
    timeout 240 python3 scripts/synthesis_speed.py --device cuda --workers 8 --batch-size 64 \
      --patch 64 --steps 30 --synthesis-batches 8 --precisions bf16 \
      --json "$out/synthesis_speed_gpu.json" \
      || echo "synthesis speed: exit $?"
    ;;
  receive)
    scripts/receive_parts.sh "$@"
    ;;
  onnx)
    export PYTHONPATH="$ort:$PYTHONPATH"
    # the CUDA libraries of torch's nvidia wheels, for every process onnxruntime-gpu runs in
    nvidia=$(python3 -c "import nvidia; print(list(nvidia.__path__)[0])")
    libs=$(find "$nvidia" -name 'lib*.so*' -printf '%h\n' | sort -u | paste -sd:)
    export LD_LIBRARY_PATH="$libs${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
    python3 -c "import onnxruntime as o; o.preload_dlls(); print(o.__version__, o.get_available_providers())" \
      | tee "$out/onnxruntime.txt"
    timeout 420 python3 -m spk2img bench --gpu-only --device cuda --out-dir "$out/bench" \
      || echo "bench: exit $?"
    timeout 150 python3 -m spk2img verify spk2img/assets/models/spk2img-default.onnx \
      --device cuda --fp16 --quick > "$out/verify_fp16_cuda.txt" 2>&1 || echo "verify: exit $?"
    ;;
  train)
    seconds=${1:?seconds}
    shift
    timeout --signal=INT "$seconds" python3 -m spk2img train --device cuda --synthesis torch \
      --no-progress "$@" || echo "train: exit $? (a run stopped by the timeout saved last.pt at its step)"
    ;;
  train-start)
    name=${1:?name} seconds=${2:?seconds}
    shift 2
    mkdir -p "$runs/$name"
    setsid nohup timeout --signal=INT "$seconds" python3 -m spk2img train --device cuda \
      --synthesis torch --no-progress --run-dir "$runs/$name" "$@" \
      > "$runs/$name/train.log" 2>&1 < /dev/null &
    echo "training $name in the background for at most $seconds s: $runs/$name"
    ;;
  train-stop)
    name=${1:?name}
    # the training process alone (timeout, its parent, would pass the signal on twice)
    pkill -INT -f "^python3 -m spk2img train .*--run-dir $runs/$name( |\$)" \
      || echo "$name: not running"
    for _ in $(seq 240); do
      pgrep -f "spk2img train .*--run-dir $runs/$name( |\$)" > /dev/null || break
      sleep 0.5
    done
    mkdir -p "$out/$name"
    for f in train.log metrics.jsonl last.pt best.pt; do
      if [ -f "$runs/$name/$f" ]; then cp "$runs/$name/$f" "$out/$name/"; fi
    done
    tail -n 3 "$runs/$name/train.log"
    ;;
  *)
    echo "unknown step $step: torch, receive, onnx, train, train-start or train-stop" >&2
    exit 2
    ;;
esac
