"""Fitting a TensoRF to a scene: the jitted step and its optimiser, the schedule (upsampling, alpha
mask, L1/TV), checkpoints and the loop."""
