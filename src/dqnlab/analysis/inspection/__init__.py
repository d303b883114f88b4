"""Q-value inspection: what several networks of a run think of the same frames."""
