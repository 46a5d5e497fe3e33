"""Does a watermark decoder read patterns tied to the image frame?

For held-out images at each size, embeds a random message with the decoder's own gradient (one informed
step at the target PSNR, as a radiance field follows that gradient), then prints where the residual's energy
lies by distance to the image border, and the bit accuracy when the decoder reads the whole encoded image
and when it reads only its centre (a crop a quarter of the side in from each edge). A decoder that reads
the frame puts the residual near the borders and reads the centre crop at chance; a shift-invariant one
spreads it and still reads the crop.

    python scripts/decoder_frame_lock.py --decoder DIR/decoder.npz --sizes 64,256 [--images 32] [--json]
"""

from __future__ import annotations

import argparse
import json

import jax.numpy as jnp
import numpy as np

from mnerf_jax.reader import decoder as dec
from mnerf_jax.reader import decoder_io
from mnerf_jax.reader.train import informed
from mnerf_jax.reader.train.cover_images import heldout_images, heldout_messages

BANDS = ((0, 4), (4, 8), (8, 16), (16, 32), (32, 64), (64, 10**6))  # distance to the border, pixels


def frame_lock_figures(loaded: decoder_io.LoadedDecoder, size: int, n: int, psnr: float) -> dict:
    images = jnp.asarray(heldout_images(n, size))
    bits = jnp.asarray(heldout_messages(n, loaded.bits))

    def read(x: jnp.ndarray) -> jnp.ndarray:
        return dec.decode_logits(loaded.variables, x, loaded.wavelet)

    encoded = informed.informed_embed(read, images, bits, psnr, 1)
    energy = np.asarray(jnp.sum((encoded - images) ** 2, -1)).mean(0)  # [H, W]
    rows, cols = np.mgrid[:size, :size]
    dist = np.minimum(np.minimum(rows, cols), np.minimum(size - 1 - rows, size - 1 - cols))
    bands = []
    for lo, hi in BANDS:
        inside = (dist >= lo) & (dist < hi)
        if inside.any():
            share = float(energy[inside].sum() / energy.sum())
            bands.append(
                {
                    "from_px": lo,
                    "to_px": min(hi, size // 2),
                    "energy_share": share,
                    "area_share": float(inside.mean()),
                }
            )
    c = size // 4

    def accuracy(x: jnp.ndarray) -> float:
        return float(jnp.mean((read(x) > 0) == (bits > 0.5)))

    return {
        "size": size,
        "images": n,
        "psnr": psnr,
        "bands": bands,
        "bit_acc_whole": accuracy(encoded),
        "bit_acc_centre_crop": accuracy(encoded[:, c : size - c, c : size - c]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--decoder", required=True, help="decoder file (.npz)")
    parser.add_argument("--sizes", default="64,256", help="image sides, comma-separated (64,256)")
    parser.add_argument("--images", type=int, default=32, help="held-out images per size (32)")
    parser.add_argument("--psnr", type=float, default=35.5, help="PSNR of the embedding (35.5)")
    parser.add_argument("--json", action="store_true", help="one JSON line per size")
    args = parser.parse_args()
    loaded = decoder_io.load_decoder(args.decoder)
    print(f"decoder {args.decoder}: {loaded.bits} bits, pooling margin {dec.pool_margin(loaded.variables)}")
    for size in (int(s) for s in args.sizes.split(",")):
        fig = frame_lock_figures(loaded, size, args.images, args.psnr)
        if args.json:
            print(json.dumps(fig))
            continue
        print(
            f"{size}²: informed 1-step bit accuracy, whole image {fig['bit_acc_whole']:.3f}, "
            f"centre crop {fig['bit_acc_centre_crop']:.3f}"
        )
        for band in fig["bands"]:
            lo, hi, energy, area = band["from_px"], band["to_px"], band["energy_share"], band["area_share"]
            print(
                f"  {lo:>3}–{hi:<3} px from the border: {energy:6.1%} of the residual energy"
                f" on {area:6.1%} of the area"
            )


if __name__ == "__main__":
    main()
