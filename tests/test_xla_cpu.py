"""``core.xla_cpu``: releasing compiled programs gives their memory maps back (in a fresh process, so that
this worker's compiled programs stay)."""

from __future__ import annotations

import subprocess
import sys
import textwrap


def test_releasing_compiled_programs_gives_their_memory_maps_back() -> None:
    script = textwrap.dedent(
        """
        import jax, jax.numpy as jnp
        from mnerf_jax.core import xla_cpu

        def maps():
            with open("/proc/self/maps") as f:
                return sum(1 for _ in f)

        before = maps()
        def program(i):
            return jax.jit(lambda x: jnp.sin(x * i) @ jnp.cos(x.T) + jnp.tanh(x).sum(0) * i)

        programs = [program(i) for i in range(24)]
        for program in programs:
            program(jnp.ones((64, 64))).block_until_ready()
        compiled = maps()
        del programs  # as a command's stages drop theirs
        xla_cpu.release_compiled()
        print(before, compiled, maps())
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        check=True,
        env={"JAX_PLATFORMS": "cpu", "PATH": "/usr/bin:/bin"},
    )
    before, compiled, released = map(int, out.stdout.split())
    assert compiled - before >= 24  # each program maps pages of its own
    assert released - before < (compiled - before) / 2, (before, compiled, released)
