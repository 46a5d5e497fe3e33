"""Phase 3 again on a finished watermarked run, with other phase-3 settings: a copy of the run whose decoder
is refitted on its field's renders from the phase-2 decoder (the field, and so the PSNR, unchanged).

For measuring a phase-3 setting without embedding again (the field is most of an embedding's time), and for
giving a run embedded before a setting existed its benefit. No time budget: ``watermark.phase3.steps`` run
in full (the plain command's budget sizes them; ``mnerf embed`` prints how many it took). The copy's
``config.json`` records the new settings; its checkpoints are the original's (their decoder is the old one:
``decoder.npz`` is what ``mnerf evaluate``, ``extract`` and ``attack`` read).

    python scripts/refit_phase3.py --run WMRUN --out NEWRUN [--field-step N]
        [--set watermark.phase3.attacked=0.5 ...]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

# Results of reading a run: they describe the old decoder, so the copy leaves them behind.
NOT_COPIED = ("eval-*", "false-claims.json", "calibration.json", "tb")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", required=True, type=Path, help="a finished watermarked run (mnerf embed)")
    parser.add_argument("--out", required=True, type=Path, help="the copy to write (must not exist)")
    parser.add_argument(
        "--field-step",
        type=int,
        default=None,
        help="the checkpoint phase 3 starts from (default: the last within the field's schedule)",
    )
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a config override")
    args = parser.parse_args(argv)

    import jax
    import jax.numpy as jnp

    from mnerf_jax.core import config as config_lib
    from mnerf_jax.core import rundir
    from mnerf_jax.core.errors import MnerfError
    from mnerf_jax.reader import decoder_io
    from mnerf_jax.reader import keys as keys_lib
    from mnerf_jax.watermark import embed, phase3
    from mnerf_jax.watermark import run as wm_run
    from mnerf_jax.watermark.inputs import clean_references
    from mnerf_jax.watermark.loop import DECODER_FILE

    try:
        marker = wm_run.require_watermarked(args.run)
        if args.out.exists():
            raise MnerfError(f"--out {args.out} exists: phase 3 is redone into a new copy")
        config = config_lib.apply_overrides(config_lib.load_json(args.run / rundir.CONFIG_FILE), args.set)
        cfg = config.watermark
        if not cfg.phase3.steps:
            raise MnerfError("watermark.phase3.steps is 0: nothing to refit (--set watermark.phase3.steps=N)")
        field_step, tree = wm_run.restore_field_end(args.run, cfg, args.field_step)
        shutil.copytree(args.run, args.out, ignore=shutil.ignore_patterns(*NOT_COPIED))
        rundir.write_json_atomic(args.out / rundir.CONFIG_FILE, config.to_dict())
        run = wm_run.load_watermarked_run(args.out)
        source = embed.load_source(marker["source_run"])
        scene = source.load_scene(None, splits=("train",))
        split = scene.split("train")
        tick = time.perf_counter()
        references = clean_references(source, split, progress=True)
        data = phase3.render_refit_set(
            run, split.cameras, cfg, split.images, source, True, references, None, scene.depth_bounds
        )
        print(f"refit_phase3: the set rendered in {time.perf_counter() - tick:.0f} s", file=sys.stderr)
        tick = time.perf_counter()
        decoder, metrics = phase3.refit_decoder(
            cfg, jax.tree.map(jnp.asarray, tree["decoder"]), data, progress=True
        )
        print(
            f"refit_phase3: {int(metrics['steps'])} decoder steps in {time.perf_counter() - tick:.0f} s "
            f"(loss {metrics['loss']:.4f})",
            file=sys.stderr,
        )
        meta = decoder_io.save_decoder(
            args.out / DECODER_FILE,
            decoder,
            {
                "embed_step": field_step + int(metrics["steps"]),
                "read_window": cfg.reading.window,
                "read_background": cfg.reading.background,
                "read_jitter": cfg.reading.jitter,
                "read_max_side": cfg.reading.max_side,
            },
            wavelet=cfg.reading.wavelet,
        )
        keys_lib.save_keys(
            args.out, keys_lib.with_fingerprint(keys_lib.load_keys(args.out), meta["fingerprint"])
        )
    except MnerfError as err:
        print(f"refit_phase3: {err}", file=sys.stderr)
        return 2
    print(f"refit_phase3: wrote {args.out} (evaluate it with `mnerf evaluate --run {args.out}`)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
