"""Training a decoder: the recipe as data, cover images, the informed and HiDDeN-encoder stages, their
jitted steps, checkpoints and held-out evaluation."""
