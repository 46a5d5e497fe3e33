"""What every layer shares and that knows nothing of the rest: errors, configs as typed data and their
I/O, run directories, Orbax checkpoints, scalar logs and the XLA:CPU options of the hot programs."""
