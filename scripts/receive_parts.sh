#!/usr/bin/env bash
# Receive a file split by `python -m spk2img.parts split` (or `spk2img pack-data`) on a machine
# that gets at most 64 MiB a command, one command per part (docs/gpu.md, "Files larger than a
# command"). Run the same line in each command, with that command's part carried beside the
# manifest: the parts gather in $PARTS_STORE (default /tmp/spk2img-parts, which lasts between
# commands while the machine is warm); the command that brings the last part joins them,
# checks every SHA-256, and unpacks into DEST:
#   a .zip (the training-data pack)       -> extracted into DEST/
#   a .tar.xz (onnxruntime-gpu for one GPU architecture, scripts/slim_onnxruntime_gpu.py)
#                                         -> extracted into DEST/ (for PYTHONPATH)
#   a .whl (e.g. onnxruntime-gpu)         -> pip install --no-deps --target DEST
#   anything else                         -> moved to DEST
# Usage: scripts/receive_parts.sh MANIFEST DEST
set -euo pipefail
manifest=$1
dest=$2
store=${PARTS_STORE:-/tmp/spk2img-parts}
python=${PYTHON:-python3}
status=$("$python" -m spk2img.parts collect "$manifest" --into "$store")
echo "$status"
[ "$status" = complete ] || exit 0
name=$(basename "$manifest" .parts.json)
"$python" -m spk2img.parts join "$store/$name.parts.json" --out "$store/$name"
case "$name" in
  *.zip) mkdir -p "$dest" && "$python" -m zipfile -e "$store/$name" "$dest" ;;
  *.tar.xz) mkdir -p "$dest" && "$python" -c "import sys, tarfile
tarfile.open(sys.argv[1]).extractall(sys.argv[2], filter='data')" "$store/$name" "$dest" ;;
  *.whl) "$python" -m pip install --quiet --no-deps --target "$dest" "$store/$name" ;;
  *) mv "$store/$name" "$dest" ;;
esac
rm -f "$store/$name" "$store/$name".part-*
echo "received $name -> $dest"
