"""Training rays on the host and the sampler that draws each step's batch from them.

``training_rays`` gathers every pixel ray of the train split (dropping rays that miss the scene box);
``PermutationSampler`` is TensoRF's SimpleSampler as a pure function of the step, so a resumed fit draws the
same batches as an uninterrupted one.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from mnerf_jax.core.errors import MnerfError
from mnerf_jax.data import Scene, all_rays
from mnerf_jax.tensorf import alpha_mask, raymarch


@dataclasses.dataclass
class RaySet:
    """Training rays on the host: ``origins``, ``directions``, ``rgb`` ``[N, 3]`` float32."""

    origins: np.ndarray
    directions: np.ndarray
    rgb: np.ndarray

    def __len__(self) -> int:
        return int(self.origins.shape[0])

    def select(self, keep: np.ndarray) -> RaySet:
        """The rays where ``keep [N]`` is True."""
        return RaySet(self.origins[keep], self.directions[keep], self.rgb[keep])


class PermutationSampler:
    """TensoRF's SimpleSampler made a function of the step: a fresh permutation every epoch.

    Batch ``j`` of epoch ``e`` (``floor(N / B)`` batches per epoch; the tail of a permutation is
    unused, as TensoRF) is ``perm(seed, start, e)[j B : (j + 1) B]``.
    """

    def __init__(self, seed: int, n_rays: int, batch: int, start: int):
        if n_rays < 1:
            raise MnerfError("no training rays left (every ray misses the scene box)")
        self.seed, self.n_rays, self.start = int(seed), int(n_rays), int(start)
        self.batch = min(int(batch), self.n_rays)
        self.per_epoch = max(self.n_rays // self.batch, 1)
        self._cached: tuple[int, np.ndarray] | None = None

    def indices(self, step: int) -> np.ndarray:
        """``[B]`` int64 ray indices of step ``step``."""
        local = step - self.start
        epoch, j = divmod(local, self.per_epoch)
        if self._cached is None or self._cached[0] != epoch:
            rng = np.random.default_rng([self.seed, 0x5A4D, self.start, epoch])
            self._cached = (epoch, rng.permutation(self.n_rays))
        return self._cached[1][j * self.batch : (j + 1) * self.batch]


def training_rays(scene: Scene, geometry: raymarch.Geometry) -> RaySet:
    """All rays of the train split; for non-NDC scenes those missing the aabb are dropped."""
    origins, directions, rgb = all_rays("train", scene)
    if not scene.ndc:
        keep = alpha_mask.filter_rays(geometry, origins, directions, chunk=1 << 20, bbox_only=True)
        if not keep.all():
            origins, directions, rgb = origins[keep], directions[keep], rgb[keep]
    return RaySet(np.ascontiguousarray(origins), np.ascontiguousarray(directions), np.ascontiguousarray(rgb))
