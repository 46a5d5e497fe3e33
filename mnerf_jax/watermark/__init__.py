"""MultiNeRF: the watermark module (grid, Emb, FiLM, variants) and its embedding into a fitted TensoRF
(the jitted step, deferred back-propagation, the sample cache, the loop, phase 3, the time budget) and the
watermarked run on disk."""
