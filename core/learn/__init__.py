"""Learning with the safety layers: RL agents, the safe-RL baselines and the Gymnasium
environments. May import every library layer below it."""
