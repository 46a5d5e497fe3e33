"""``python -m mnerf_jax.cli``: the ``mnerf`` command line."""

import sys

from mnerf_jax.cli import main

sys.exit(main())
