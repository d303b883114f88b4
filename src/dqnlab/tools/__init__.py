"""Tools over runs: reports, Q-value inspection, videos, ablations, the benchmark and the
Stable-Baselines3 comparison."""
