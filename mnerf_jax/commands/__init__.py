"""Subcommands of ``mnerf``. Each module defines ``NAME``, ``HELP``, ``add_arguments(parser)`` and
``run(args) -> int``; ``mnerf_jax.cli`` lists them in ``COMMAND_MODULES``."""
