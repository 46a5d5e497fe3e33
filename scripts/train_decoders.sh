#!/usr/bin/env bash
# Train the shipped HiDDeN decoders and copy them, with their check batches and encoders, into the package.
# Usage: [BITS="8 32"] scripts/train_decoders.sh [OUT_DIR] [extra train-decoder flags, e.g. --images DIR]
# BITS names the message lengths to (re)train, 8, 16, 32 and 48 by default (times: docs/decoders.md); a
# length ships once decoder_io.SHIPPED_BITS names it.
# A killed run continues where it stopped when the script is run again (the runs resume).
# Each decoder then gets a wider, deeper HiDDeN encoder refitted for it: up to 16 bits the decoder is copied
# unchanged (docs/decoders.md, "The encoder refit"); from 32 bits the decoder learns too once the encoder
# writes for it, over 12,000 steps (docs/decoders.md, "The joint refit").
set -euo pipefail
out="${1:-decoder-runs}"
shift || true
assets="$(dirname "$0")/../mnerf_jax/assets/decoders"
mkdir -p "$out" "$assets"
resume_flag() { if [[ -f "$1/checkpoint.msgpack" ]]; then echo --resume; fi; }
for bits in ${BITS:-8 16 32 48}; do
  run="$out/l$bits"
  # shellcheck disable=SC2046
  mnerf train-decoder --bits "$bits" --out "$run" --informed-steps 4000 --steps 0 --finetune-steps 5000 \
    $(resume_flag "$run") "$@"
  refit="$out/l${bits}_refit"
  refit_steps=(--finetune-steps 5000)
  if ((bits >= 32)); then
    refit_steps=(--finetune-steps 12000 --finetune-decoder-lr 1e-4 --finetune-decoder-start 0.15)
  fi
  # shellcheck disable=SC2046
  mnerf train-decoder --bits "$bits" --out "$refit" --informed-steps 0 --steps 0 "${refit_steps[@]}" \
    --decoder-from "$run/decoder.npz" --encoder-channels 64 --encoder-depth 4 $(resume_flag "$refit") "$@"
  run="$refit"
  cp "$run/decoder.npz" "$assets/hidden_l$bits.npz"
  cp "$run/check.npz" "$assets/hidden_l${bits}_check.npz"
  cp "$run/encoder.npz" "$assets/hidden_l${bits}_encoder.npz"
done
