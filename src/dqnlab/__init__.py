"""dqnlab: the Nature DQN exactly as DeepMind ran it, fast, on Atari or any Gymnasium env."""

__version__ = "0.1.0"
