#!/usr/bin/env bash
# Train the two shipped HiDDeN decoders (16 and 48 bits) and copy them, with their check batches, into the
# package. Usage: scripts/train_decoders.sh [OUT_DIR] [extra train-decoder flags, e.g. --images ~/coco/train2014]
# A killed run continues where it stopped when the script is run again (the runs are resumed).
# Each decoder then gets a wider, deeper HiDDeN encoder refitted for it: for 16 bits the decoder is copied
# unchanged (docs/decoders.md, "The encoder refit"); for 48 bits the decoder learns too once the encoder
# writes for it, over 12,000 steps (docs/decoders.md, "The joint refit").
set -euo pipefail
out="${1:-decoder-runs}"
shift || true
assets="$(dirname "$0")/../mnerf_jax/assets/decoders"
mkdir -p "$out" "$assets"
resume_flag() { if [[ -f "$1/checkpoint.msgpack" ]]; then echo --resume; fi; }
for bits in 16 48; do
  run="$out/l$bits"
  # shellcheck disable=SC2046
  mnerf train-decoder --bits "$bits" --out "$run" --informed-steps 4000 --steps 0 --finetune-steps 5000 \
    $(resume_flag "$run") "$@"
  refit="$out/l${bits}_refit"
  refit_steps=(--finetune-steps 5000)
  if [[ "$bits" == 48 ]]; then
    refit_steps=(--finetune-steps 12000 --finetune-decoder-lr 1e-4 --finetune-decoder-start 0.15)
  fi
  # shellcheck disable=SC2046
  mnerf train-decoder --bits "$bits" --out "$refit" --informed-steps 0 --steps 0 "${refit_steps[@]}" \
    --decoder-from "$run/decoder.npz" --encoder-channels 64 --encoder-depth 4 $(resume_flag "$refit") "$@"
  run="$refit"
  cp "$run/decoder.npz" "$assets/hidden_l$bits.npz"
  cp "$run/check.npz" "$assets/hidden_l${bits}_check.npz"
done
