"""A run in time and on disk: its directory, the algorithm's state and steps, the training
loop, evaluation, checkpoints and logs."""
