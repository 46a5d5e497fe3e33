"""The ``mnerf`` command line: a thin dispatcher over ``mnerf_jax.cli.*`` (one module per command)."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from mnerf_jax.core.errors import MnerfError

# Each module defines NAME, HELP, add_arguments(parser) and run(args) -> int. Modules are imported
# lazily per command so that `mnerf --help` does not pay for importing JAX.
COMMAND_MODULES: dict[str, str] = {
    "demo": "mnerf_jax.cli.demo",
    "fit": "mnerf_jax.cli.fit",
    "render": "mnerf_jax.cli.render",
    "evaluate": "mnerf_jax.cli.evaluate",
    "attack": "mnerf_jax.cli.attack",
    "train-decoder": "mnerf_jax.cli.train_decoder",
    "extract": "mnerf_jax.cli.extract",
    "embed": "mnerf_jax.cli.embed",
    "compare": "mnerf_jax.cli.compare",
    "study": "mnerf_jax.cli.study",
}


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mnerf",
        description="Fit TensoRF radiance fields, embed keyed watermarks, render and extract them.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module_name in COMMAND_MODULES.items():
        if selected is not None and name != selected:
            sub.add_parser(name, help="")
            continue
        module = importlib.import_module(module_name)
        command = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(command)
        command.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    selected = next((a for a in argv if a in COMMAND_MODULES), None)
    try:
        parser = build_parser(selected)
    except ModuleNotFoundError as err:
        print(f"mnerf: error: command {selected!r} is not available ({err})", file=sys.stderr)
        return 2
    args = parser.parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except MnerfError as err:
        print(f"mnerf: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mnerf: interrupted (the last checkpoint is kept; rerun with --resume)", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
