"""The environments through Gymnasium: registration, the env checker, vector envs, the cost in info."""
import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import skinsafe.core.learn  # noqa: F401  (registers the environments)
from skinsafe.core.learn.tracking_env import TrackingEnv


def test_maze_registered_checked_and_vectorised():
    env = gym.make("skinsafe/Maze-v0", max_steps=30)
    check_env(env.unwrapped, skip_render_check=True)
    vec = gym.make_vec("skinsafe/Maze-v0", num_envs=2, vectorization_mode="sync", max_steps=30)
    obs, _ = vec.reset(seed=0)
    assert obs.shape == (2, 4)
    costs = []
    for _ in range(6):  # both robots drive forward from the start: free, free, then the wall
        obs, r, term, trunc, info = vec.step(np.zeros(2, int))
        costs.append(info["cost"])
    costs = np.array(costs)
    assert costs.shape == (6, 2) and costs[:2].sum() == 0 and costs[2:].min() == 1.0
    vec.close()


def test_module_qualified_id_imports_the_registration():
    env = gym.make("skinsafe.core.learn:skinsafe/Maze-v0")
    assert env.unwrapped.max_steps == 100


@pytest.fixture(scope="module")
def tracking():
    return TrackingEnv(pitch=0.02, duration=1.0)


def test_tracking_env_checked_and_the_balls_are_on_the_path(tracking):
    check_env(tracking, skip_render_check=True)
    obs, _ = tracking.reset(seed=3)
    again, _ = tracking.reset(seed=3)
    np.testing.assert_array_equal(obs, again)
    steps, cost = 0, 0.0
    while True:
        obs, r, term, trunc, info = tracking.step(tracking.nominal(obs))
        steps, cost = steps + 1, cost + info["cost"]
        assert r <= 0 and info["taxel_danger"].dtype == bool and info["cost"] == float(info["taxel_danger"].any())
        if trunc:
            break
    assert steps == tracking.task.ticks == 50
    assert tracking.scene.path_contact_ticks() > 5 and cost > 5  # exact tracking must touch the balls
    assert tracking.step(np.full(6, np.nan))[4]["cost"] in (0.0, 1.0)  # a broken command holds the joints


def test_tracking_in_a_vector_env():
    vec = gym.vector.SyncVectorEnv([lambda: TrackingEnv(pitch=0.02, duration=0.2)] * 2)
    obs, _ = vec.reset(seed=0)
    obs, r, term, trunc, info = vec.step(np.zeros((2, 6), np.float32))
    assert obs.shape == (2, 18) and info["cost"].shape == (2,)
    vec.close()
