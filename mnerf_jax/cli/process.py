"""Process settings every heavy command starts with (glibc huge pages for XLA:CPU's buffers)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

# What ``python -m mnerf_jax.cli`` runs as ``__main__``.
_CLI_MODULES = ("mnerf_jax.cli", "mnerf_jax.cli.__main__")

HUGE_PAGE_TUNABLE = "glibc.malloc.hugetlb=1"
_REEXEC_MARK = "MNERF_ALLOCATOR_REEXEC"


def _huge_pages_on() -> bool:
    return "glibc.malloc.hugetlb" in os.environ.get("GLIBC_TUNABLES", "")


def reexec_with_huge_pages(argv: list[str] | None = None) -> None:
    """Restart the ``mnerf`` process once with glibc's transparent-huge-page tunable (Linux only).

    XLA:CPU allocates each call's temporary buffers with malloc; glibc serves large blocks with
    fresh mmaps and unmaps them on free, so every train step faults its working set in again, 4 KiB
    at a time. With ``GLIBC_TUNABLES=glibc.malloc.hugetlb=1`` those mappings use 2 MiB pages, which
    removes most of those page faults. The tunable is read at process start, hence the re-exec.

    ``argv``: the command that restarts this process (a script passes its own); by default only the
    ``mnerf`` command-line process restarts itself (never a caller of ``cli.main``, such as tests).
    """
    if not sys.platform.startswith("linux") or _huge_pages_on() or os.environ.get(_REEXEC_MARK):
        return
    if argv is None:
        main = sys.modules.get("__main__")
        spec = getattr(main, "__spec__", None)
        if not ((spec is not None and spec.name in _CLI_MODULES) or Path(sys.argv[0]).name == "mnerf"):
            return
        argv = [sys.executable, "-m", "mnerf_jax.cli", *sys.argv[1:]]
    env = dict(os.environ)
    tunables = env.get("GLIBC_TUNABLES", "")
    env["GLIBC_TUNABLES"] = f"{tunables}:{HUGE_PAGE_TUNABLE}" if tunables else HUGE_PAGE_TUNABLE
    env[_REEXEC_MARK] = "1"
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(argv[0], argv, env)


def prepare_process() -> None:
    """Process settings for a command: glibc huge pages for XLA's buffers (see ``reexec_with_huge_pages``)."""
    reexec_with_huge_pages()
