"""The TensoRF (VM) radiance field: factor grids, the field and its colour MLP, ray marching,
compositing, static sample budgets, the alpha mask, and a fitted run loaded for rendering. Knows nothing of
watermarks; ``tensorf.fit`` trains a field."""
