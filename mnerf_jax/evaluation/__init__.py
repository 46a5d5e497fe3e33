"""Evaluating fitted and watermarked runs: bit accuracy, identification and quality on a split, attacks,
reports and plots, runs compared side by side."""
