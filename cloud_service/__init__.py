"""The cloud: the measurement memory, the online SINR map and value-network training."""
