"""mnerf-jax: MultiNeRF (multiple keyed watermarks in a TensoRF radiance field) in JAX/Flax."""

__version__ = "0.1.0"
