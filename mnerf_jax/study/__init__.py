"""Studies: a grid of watermarking runs (scenes × methods × IDs × bit lengths × seeds) run, resumed and
sharded as one, with every cell's figures in one tidy table beside the paper's published numbers
(``mnerf study``)."""
