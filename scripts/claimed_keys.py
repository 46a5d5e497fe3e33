"""Which keys the clean model's attacked renders are named as, through each decoder a run has had.

A false claim under an attack is the decision naming a key on an unwatermarked image that went through it.
This reads the run's saved clean test renders (``mnerf evaluate``) after each attack of ``--suite`` (under
``--seeds`` draws of the attack) through three decoders: the run's own (``decoder.npz``, after phase 3),
its decoder at the end of the field's schedule (the checkpoint phase 3 started from) and the shipped
decoder the embedding started from; and prints, per attack and decoder, how many renders were named and as
which key, and how many renders were named under more than one draw.

    python scripts/claimed_keys.py --run WMRUN [--split test] [--suite peers]
        [--attacks gaussian_noise0.1,brightness2] [--seeds 4] [--threshold P] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--run", required=True, type=Path, help="a watermarked run with `mnerf evaluate` done"
    )
    parser.add_argument("--split", default="test", help="the evaluated split whose clean renders are read")
    parser.add_argument("--suite", default="peers", help="the attack suite the attacks come from")
    parser.add_argument("--attacks", default="", help="comma-separated attacks of the suite (default: all)")
    parser.add_argument("--seeds", type=int, default=4, help="draws of each attack (seeds 0 .. N-1)")
    parser.add_argument(
        "--threshold", type=float, default=None, help="name below this corrected p-value (default: the run's)"
    )
    parser.add_argument("--json", type=Path, default=None, help="also write the counts here")
    args = parser.parse_args(argv)

    import dataclasses

    import jax
    import jax.numpy as jnp
    import numpy as np

    from mnerf_jax.core import rundir
    from mnerf_jax.core.errors import MnerfError
    from mnerf_jax.evaluation import attacks as attack_eval
    from mnerf_jax.evaluation import watermarked as wm_eval
    from mnerf_jax.reader import extract, identification
    from mnerf_jax.watermark import decision
    from mnerf_jax.watermark import run as wm_run

    try:
        keys, decoder = wm_run.load_keys_and_decoder(args.run)
        wm = rundir.read_run_config(args.run).watermark
        rule = decision.decision_rule(args.run, wm.reading, decoder.fingerprint, args.threshold)
        field_step, tree = wm_run.restore_field_end(args.run, wm)
        decoders = {
            "run": decoder,
            f"field end (step {field_step})": dataclasses.replace(
                decoder, variables=jax.tree.map(jnp.asarray, tree["decoder"])
            ),
            "shipped": extract.resolve_decoder(None, keys.bits),
        }
        folder = args.run / f"eval-{args.split}" / attack_eval.CLEAN_FOLDER
        names = sorted(p.stem for p in folder.glob("*.png"))
        clean = attack_eval.saved_clean(args.run, args.split, names) if names else None
        if clean is None:
            raise MnerfError(f"{folder}: no clean renders (run `mnerf evaluate --run {args.run}` first)")
        chosen, _ = attack_eval.choose_attacks(args.suite)
        wanted = [a for a in args.attacks.split(",") if a]
        attacks = [a for a in chosen if not wanted or a.name in wanted]
        missing = sorted(set(wanted) - {a.name for a in attacks})
        if missing:
            raise MnerfError(f"not in the {args.suite} suite: {', '.join(missing)}")
    except MnerfError as err:
        print(f"claimed_keys: {err}", file=sys.stderr)
        return 2

    messages = np.asarray(keys.messages, np.float32)
    rows: list[dict[str, Any]] = []
    print(
        f"{len(clean)} clean renders of {args.run}, {args.seeds} draws of each attack, p < {rule.threshold:g}"
    )
    for attack in attacks:
        attacked = [attack(clean, seed) for seed in range(args.seeds)]
        for label, dec in decoders.items():
            per_key = np.zeros(keys.num_ids, int)
            per_render = np.zeros(len(clean), int)
            for images in attacked:
                logits = wm_eval.decode_renders(dec, wm, images.astype(np.float32) / 255.0, batch=32)
                named = identification.identify_logits(logits, messages, rule.threshold, rule.test).decision
                per_key += np.bincount(named[named >= 0], minlength=keys.num_ids)
                per_render += named >= 0
            rows.append(
                {
                    "attack": attack.name,
                    "decoder": label,
                    "reads": len(clean) * args.seeds,
                    "named": int(per_key.sum()),
                    "named_per_key": per_key.tolist(),
                    "renders_named_more_than_once": int((per_render > 1).sum()),
                }
            )
            keys_named = ", ".join(f"ID {k}: {c}" for k, c in enumerate(per_key) if c) or "none"
            print(
                f"{attack.name:<34} {label:<22} named {per_key.sum():>4} of {len(clean) * args.seeds}"
                f" ({keys_named}); renders named under more than one draw: {(per_render > 1).sum()}"
            )
    if args.json:
        args.json.write_text(json.dumps({"run": str(args.run), "seeds": args.seeds, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
