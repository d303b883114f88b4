"""The figures of `dqnlab bench`: throughput, memory, the compressed replay, Ray, SB3's DQN."""
