#!/usr/bin/env bash
# Train the two shipped HiDDeN decoders (16 and 48 bits) and copy them, with their check batches, into the
# package. Usage: scripts/train_decoders.sh [OUT_DIR] [extra train-decoder flags, e.g. --images ~/coco/train2014]
# A killed run continues where it stopped when the script is run again (the runs are resumed).
set -euo pipefail
out="${1:-decoder-runs}"
shift || true
assets="$(dirname "$0")/../mnerf_jax/assets/decoders"
mkdir -p "$out" "$assets"
for bits in 16 48; do
  run="$out/l$bits"
  resume=()
  if [[ -f "$run/checkpoint.msgpack" ]]; then resume=(--resume); fi
  mnerf train-decoder --bits "$bits" --out "$run" --informed-steps 4000 --steps 0 --finetune-steps 5000 "${resume[@]}" "$@"
  cp "$run/decoder.npz" "$assets/hidden_l$bits.npz"
  cp "$run/check.npz" "$assets/hidden_l${bits}_check.npz"
done
