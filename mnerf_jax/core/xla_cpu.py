"""XLA:CPU compiler options for the project's hot jitted functions (renders, steps, the decoder).

XLA:CPU (jax 0.10) hands elementwise+reduce subgraphs, and the ops around convolutions, to YNNPACK fusions.
For this code they are slower: the renderer's sampled features are materialised (below), and the decoder's
3×3 convolutions run slower with them than without.
"""

from __future__ import annotations

import functools
import gc
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

# XLA:CPU (jax 0.10) hands elementwise+reduce subgraphs to YNNPACK fusions, which materialise every
# gathered [P, C] operand and so slow the density forward and evaluation renders (training steps hardly
# change). Disabling them per compilation restores XLA's own fused loops.
# A harness may add options here before the first compilation (tests/conftest.py compiles these hot paths
# at XLA's backend optimisation level 1 and everything else at level 0).
CPU_OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": ""}


@functools.cache
def xla_compiler_options() -> dict[str, str]:
    """Compiler options for ``jax.jit(..., compiler_options=...)`` of rendering code.

    On CPU, the options that keep XLA from routing sampled-feature arithmetic through YNNPACK
    fusions, if this XLA accepts them; ``{}`` elsewhere. Pass them to the ``jax.jit`` of any function
    that calls ``render_rays`` or the decoder (the options of an inner jit are ignored when it is
    inlined).
    """
    if jax.default_backend() != "cpu":
        return {}
    try:
        jax.jit(lambda x: x + 1, compiler_options=CPU_OPTIONS).lower(jnp.zeros(2)).compile()
    except Exception:  # an XLA without this option: keep its defaults
        return {}
    return dict(CPU_OPTIONS)


def jit_cpu_tuned(fun: Callable | None = None, **kwargs: Any) -> Any:
    """``jax.jit`` with ``xla_compiler_options()`` when called at top level (chosen at the first call).

    Inside another transformation (arguments are tracers) the plain ``jax.jit`` is used: JAX accepts
    compiler options only on the outermost jit, whose owner should pass ``xla_compiler_options()``.
    """
    if fun is None:
        return functools.partial(jit_cpu_tuned, **kwargs)
    plain = jax.jit(fun, **kwargs)
    top: list[Callable] = []

    @functools.wraps(fun)
    def wrapper(*args: Any, **kw: Any) -> Any:
        if any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves((args, kw))):
            return plain(*args, **kw)
        if not top:
            top.append(jax.jit(fun, compiler_options=xla_compiler_options(), **kwargs))
        return top[0](*args, **kw)

    return wrapper


def release_compiled() -> None:
    """Drop every compiled program and what only they reference.

    XLA:CPU maps each compiled kernel's code into pages of its own, so a process that compiles many programs
    (an embedding's steps, phase 3, then an evaluation's renders) can reach the kernel's limit on memory maps
    (``vm.max_map_count``), where the next compilation fails ("LLVM compilation error: Cannot allocate
    memory"). A command calls this between stages that share no compiled program.
    """
    gc.collect()
    jax.clear_caches()
    gc.collect()
