"""The algorithm: the Q-networks, the optimizers, the replay memory and the agent
(acting and the update)."""
