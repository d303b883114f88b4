"""The figures of `dqnlab bench`: throughput, memory, the compressed replay, several
environments, the DQN family, the stop checkpoint, the GPU path, and the peers (SB3's and
CleanRL's DQN) measured alike."""
