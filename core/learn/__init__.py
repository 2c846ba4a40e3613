"""Learning with the safety layers: RL agents, the safe-RL baselines, online TDM training and the
Gymnasium environments. May import every library layer below it.

Importing this package registers the environments with Gymnasium:
`gym.make("skinsafe/Maze-v0")` (the strategy-layer maze, Fig. 9) and `gym.make("skinsafe/Tracking-v0")`
(UR5 tracking among balls, Fig. 11); without importing it first, name the module in the id:
`gym.make("skinsafe.core.learn:skinsafe/Maze-v0")`. Both report the safety cost in `info["cost"]`.
"""
from gymnasium.envs.registration import register, registry

for _id, _entry in (("skinsafe/Maze-v0", "skinsafe.core.learn.maze_env:MazeEnv"),
                    ("skinsafe/Tracking-v0", "skinsafe.core.learn.tracking_env:TrackingEnv")):
    if _id not in registry:
        register(id=_id, entry_point=_entry)
