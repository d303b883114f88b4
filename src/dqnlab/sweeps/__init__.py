"""Grids of runs as Ray tasks, on this machine or a cluster: sweeps and ablations."""
