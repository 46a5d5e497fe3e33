"""Sample budgets of the TensoRF train step: the static sizes of its compacted sample buffers.

``render_rays`` compacts the samples inside the alpha mask (density) and those with weight > 1e-4 (colour)
into buffers of static size, so each size is one compilation. ``SampleBudgets`` sizes them at the start of
each phase from a probe of the rays (``estimate_density_count``), grows them when a step overflows (the step
is redone, so no sample is dropped) and shrinks them at refit points, all on a coarse ladder of sizes.
``BudgetPolicy`` does the same per call site for evaluation renders (``chunked``), from the counts alone.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mnerf_jax.tensorf import raymarch
from mnerf_jax.tensorf.sampler import RaySet

Array = jax.Array


def ladder_budget(needed: float, steps_per_octave: int = 4, minimum: int = 1024) -> int:
    """Smallest budget ``>= needed`` of the form ``m 2^k``, ``steps_per_octave <= m < 2 steps_per_octave``.

    A coarse ladder keeps the number of distinct static shapes (compilations) small while wasting at
    most ``1 / steps_per_octave`` of the buffer. ``steps_per_octave=1`` gives powers of two.
    """
    needed = max(float(needed), float(minimum), 1.0)
    k = max(math.floor(math.log2(needed / steps_per_octave)), 0)
    while True:
        for m in range(steps_per_octave, 2 * steps_per_octave):
            if m * 2**k >= needed:
                return int(m * 2**k)
        k += 1


@dataclasses.dataclass
class _Site:
    density: int
    colour: int
    seen_density: int = 0
    seen_colour: int = 0
    calls: int = 0
    fresh: bool = True  # budgets not yet fitted to observed counts


class BudgetPolicy:
    """Static density/colour budgets per call site that grow on overflow and shrink when oversized.

    Usage::

        policy = BudgetPolicy()
        while True:
            db, cb = policy.budgets("train", n_rays, geometry.n_samples)
            out = step(..., density_budget=db, colour_budget=cb)   # budgets are static args
            if not policy.update("train", out, n_rays, geometry.n_samples):  # False: nothing dropped
                break

    A grown budget is ``ladder_budget(count * headroom)`` (one compilation per distinct size). When
    the largest count of the last ``patience`` calls (the first ``fresh_calls`` calls for fresh budgets) times
    ``headroom`` is below ``shrink_below`` of a budget, it shrinks to fit, unless that frees fewer than
    ``min_shrink`` slots (a compilation costs seconds, a few thousand slots save little a call, so small
    renders keep their first budgets). Budgets never exceed
    ``n_rays * n_samples``, which cannot overflow: a site starts there for density (and at
    ``colour_fraction`` of it for colour), or, when only the sample count changed (upsampling), at its
    previous budgets scaled by the ratio of sample counts.
    """

    def __init__(
        self,
        headroom: float = 1.2,
        patience: int = 50,
        shrink_below: float = 0.75,
        steps_per_octave: int = 4,
        minimum: int = 1024,
        colour_fraction: float = 0.125,
        min_shrink: int = 1 << 15,
        fresh_calls: int = 5,
    ) -> None:
        self.headroom = headroom
        self.fresh_calls = fresh_calls
        self.min_shrink = min_shrink
        self.patience = patience
        self.shrink_below = shrink_below
        self.steps_per_octave = steps_per_octave
        self.minimum = minimum
        self.colour_fraction = colour_fraction
        self._sites: dict[tuple[str, int], _Site] = {}
        self._latest: dict[str, tuple[str, int]] = {}

    def _ladder(self, needed: float, cap: int) -> int:
        return min(ladder_budget(needed, self.steps_per_octave, self.minimum), cap)

    def budgets(self, site: str, n_rays: int, n_samples: int) -> tuple[int, int]:
        """``(density_budget, colour_budget)`` for a call rendering ``n_rays`` x ``n_samples``."""
        cap = n_rays * n_samples
        state = self._sites.get((site, cap))
        if state is None:
            previous = self._sites.get(self._latest.get(site, ("", -1)))
            if previous is None:
                state = _Site(density=cap, colour=self._ladder(cap * self.colour_fraction, cap))
            else:
                ratio = cap / self._latest[site][1]
                state = _Site(
                    density=self._ladder(previous.density * ratio, cap),
                    colour=self._ladder(previous.colour * ratio, cap),
                )
            self._sites[(site, cap)] = state
        self._latest[site] = (site, cap)
        return state.density, state.colour

    def update(self, site: str, out: dict[str, Any], n_rays: int, n_samples: int) -> bool:
        """Record a call's sample counts; True when it overflowed (re-run it with the new budgets)."""
        cap = n_rays * n_samples
        state = self._sites[(site, cap)]
        d_count, c_count = int(out["density_count"]), int(out["colour_count"])
        overflow = d_count > state.density or c_count > state.colour
        if d_count > state.density:
            state.density = self._ladder(d_count * self.headroom, cap)
        if c_count > state.colour:
            state.colour = self._ladder(c_count * self.headroom, cap)
        if overflow:
            state.seen_density = state.seen_colour = state.calls = 0
            return True
        state.seen_density = max(state.seen_density, d_count)
        state.seen_colour = max(state.seen_colour, c_count)
        state.calls += 1
        if state.calls >= (min(self.fresh_calls, self.patience) if state.fresh else self.patience):
            for name in ("density", "colour"):
                seen, current = getattr(state, f"seen_{name}") * self.headroom, getattr(state, name)
                fitted = self._ladder(seen, cap)
                if seen < self.shrink_below * current and current - fitted >= self.min_shrink:
                    setattr(state, name, fitted)
            state.seen_density = state.seen_colour = state.calls = 0
            state.fresh = False
        return False


def ladder(needed: float, minimum: int = 1024) -> int:
    """Smallest size ``>= needed`` on a ladder of 2 sizes per octave (2^k and 1.5 * 2^k).

    Few distinct sizes keep recompilations rare; at most a third of a buffer is slack.
    """
    return ladder_budget(needed, steps_per_octave=2, minimum=minimum)


@dataclasses.dataclass
class SampleBudgets:
    """Density / colour buffer sizes of the train step.

    Every new size costs a compilation (seconds on a CPU), so sizes change rarely: set at the start
    of a phase (new grid or alpha mask) from estimates, grown after an overflow (the step is redone),
    shrunk at a few refit points when at most half used and the phase has steps left to profit.
    A refit decided from the counts of step k takes effect at step k + 2 (step k + 1 may already be
    running: the loop is pipelined), whether or not the loop paused in between. All of it is a
    function of the observed counts and is checkpointed, so a resumed run compiles and computes
    exactly as the uninterrupted one.
    """

    density: int
    colour: int
    peak_density: int = 0
    peak_colour: int = 0
    next_step: int = -1  # a refit (next_density, next_colour) takes effect at this step; -1: none
    next_density: int = 0
    next_colour: int = 0
    last_colour: int = 0  # colour count of the latest applied step ...
    last_samples: int = 0  # ... and its samples per ray (to scale it to a new grid)
    headroom: float = 1.25  # slack over the largest count seen when a budget is refitted
    growth: float = 1.5  # after an overflow: the count times this (counts rise fast early on)
    shrink_below: float = 0.5  # refit only budgets used below this fraction ...
    shrink_large_to: float = 0.75  # ... or, from LARGE_BUDGET slots on, when the new size is at most this
    # ... and only when the slots freed times the steps left in the phase reach this many: about what one
    # compilation of the train step costs in sample-slot evaluations, so a smaller buffer repays its compile.
    refit_cost_slot_steps: int = 1 << 23

    def for_step(self, step: int) -> tuple[int, int]:
        """``(density, colour)`` budgets for dispatching step ``step`` (no side effects).

        Colour is only evaluated at samples that had a density, so its budget never exceeds that.
        """
        if 0 <= self.next_step <= step:
            return self.next_density, min(self.next_colour, self.next_density)
        return self.density, min(self.colour, self.density)

    def start_phase(self, density_estimate: float, colour_estimate: float, cap: int) -> None:
        """Budgets for a new phase from estimated counts; forget peaks and pending refits."""
        self.density = min(cap, ladder(density_estimate))
        self.colour = min(cap, ladder(colour_estimate))
        self.peak_density = self.peak_colour = 0
        self.next_step = -1

    def colour_estimate(self, n_samples: int) -> float | None:
        """The latest colour count scaled to ``n_samples`` per ray, with headroom (None: none seen)."""
        if self.last_samples <= 0:
            return None
        return self.last_colour * n_samples / self.last_samples * self.headroom

    def observe(self, step: int, density_count: int, colour_count: int, n_samples: int, cap: int) -> bool:
        """Record the counts of step ``step``; on overflow grow the budgets and return True (redo it)."""
        used = self.for_step(step)
        if density_count > used[0] or colour_count > used[1]:
            if density_count > used[0]:
                self.density = min(cap, max(self.density, ladder(density_count * self.growth)))
            if colour_count > used[1]:
                self.colour = min(cap, max(self.colour, ladder(colour_count * self.growth)))
            self.next_step = -1
            return True
        self.peak_density = max(self.peak_density, density_count)
        self.peak_colour = max(self.peak_colour, colour_count)
        self.last_colour, self.last_samples = colour_count, n_samples
        if 0 <= self.next_step <= step + 1:  # the refit is in use from the next step on: commit it
            self.density, self.colour, self.next_step = self.next_density, self.next_colour, -1
        return False

    def schedule_refit(self, effective_step: int, cap: int, remaining: int) -> None:
        """From ``effective_step`` on, shrink budgets whose peak use since the last refit is low.

        ``remaining``: steps left in the phase; a refit whose freed slots times ``remaining`` stay below
        ``refit_cost_slot_steps`` would cost more compilation than the smaller buffers save.
        """
        sizes = []
        for name in ("density", "colour"):
            peak, size = getattr(self, f"peak_{name}"), getattr(self, name)
            fitted = min(cap, ladder(peak * self.headroom))
            if size >= LARGE_BUDGET:  # every step's share of the slack is large: a smaller rung pays
                worth = fitted <= self.shrink_large_to * size
            else:
                worth = peak * self.headroom < self.shrink_below * size
            sizes.append(fitted if peak and worth else size)
        freed = self.density + self.colour - sum(sizes)
        if freed * remaining < self.refit_cost_slot_steps:
            sizes = [self.density, self.colour]
        self.peak_density = self.peak_colour = 0
        if tuple(sizes) != (self.density, self.colour):
            self.next_step, self.next_density, self.next_colour = effective_step, sizes[0], sizes[1]

    def to_dict(self) -> dict[str, int]:
        names = (
            "density",
            "colour",
            "peak_density",
            "peak_colour",
            "next_step",
            "next_density",
            "next_colour",
            "last_colour",
            "last_samples",
        )
        return {name: getattr(self, name) for name in names}


REFIT_AFTER = (8, 32, 100)  # steps into a phase at which budgets may shrink ...
REFIT_EVERY = 250  # ... and then every this many steps ...
REFIT_EVERY_LARGE = 25  # ... or this many while a budget has LARGE_BUDGET slots or more
# From this size colour dominates a step, so a recompilation is repaid within a few dozen steps; the colour
# count falls steeply while a field sharpens, which refits only at REFIT_AFTER / REFIT_EVERY would miss.
# render.colour_in_chunks skips chunks past the count, so colour slack costs little and these refits save
# less.
LARGE_BUDGET = 1 << 19


def refit_due(step: int, phase_start: int, budgets: SampleBudgets | None = None) -> bool:
    """Whether budgets are refitted after ``step`` steps (a phase began at ``phase_start``)."""
    local = step - phase_start
    if local in REFIT_AFTER or (local > 0 and local % REFIT_EVERY == 0):
        return True
    large = budgets is not None and max(budgets.density, budgets.colour) >= LARGE_BUDGET
    return large and local > 0 and local % REFIT_EVERY_LARGE == 0


@functools.partial(jax.jit, static_argnames=("n_samples",))
def _valid_samples_per_ray(
    rays_o: Array, rays_d: Array, geometry: raymarch.Geometry, key: Array, n_samples: int
) -> Array:
    """``[R]`` int32: training samples of each ray inside the aabb and the alpha mask (density count)."""
    t, _, _ = raymarch.sample_along_rays(rays_o, rays_d, geometry, key, n_samples)
    xyz = rays_o[:, None, :] + rays_d[:, None, :] * t[..., None]
    valid = raymarch.inside_box(xyz, geometry.aabb) & raymarch.alpha_mask_lookup(geometry, xyz)
    return jnp.sum(valid, axis=-1, dtype=jnp.int32)


def estimate_density_count(
    rays: RaySet, geometry: raymarch.Geometry, batch: int, seed: int, salt: int, probe: int = 8192
) -> float:
    """A high quantile (mean + 4 sd) of a batch's density count, from ``probe`` random rays.

    The count depends on the geometry and the rays only, not on the field, so this predicts the
    density budget of a phase before its first step.
    """
    rng = np.random.default_rng([seed, 0xB0D6, salt])
    idx = rng.choice(len(rays), size=min(probe, len(rays)), replace=False)
    key = jax.random.fold_in(jax.random.key(seed), salt)
    counts = np.asarray(
        _valid_samples_per_ray(
            jnp.asarray(rays.origins[idx]),
            jnp.asarray(rays.directions[idx]),
            geometry,
            key,
            n_samples=geometry.n_samples,
        ),
        np.float64,
    )
    return batch * counts.mean() + 4.0 * np.sqrt(batch) * counts.std() + 1.0
