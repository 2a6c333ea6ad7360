"""The Furuta pendulum of docs/examples/furuta.xml as a task: balance the pendulum upright.

The mechanism, its masses, damping and motor come from the MJCF file (``Scene.from_mjcf``); the task
adds what the agent sees, does and is rewarded for.
Action: Box(-1, 1, (1,)): MuJoCo's ctrl of the "torque" motor (torque = gear · ctrl = 0.3·a N·m: the
  import gives the drive max_effort = gear · 1, by which the default ``controls`` scales actions).
Observation: [cos φ, sin φ, θ, φ̇, θ̇] (motor angle φ, pivot angle θ [rad], rates [rad/s]), in the
  file's joint order, which is MuJoCo's qpos order.
Reward: 1 per step − 0.01·a².  Termination: |θ| > 0.3 rad.  Truncation: 200 steps (4 s).
Reset: φ, θ, φ̇, θ̇ ~ U(−0.05, 0.05).
"""
from pathlib import Path

import gymnasium as gym
import numpy as np

import abd_gym as ag
from abd_gym import mjcf
from abd_gym.vector.vector_env import ABDEnv, ABDVectorEnv

ENV_ID = "abd_gym_examples/FurutaMJCF-v0"
MODEL = Path(__file__).with_name("furuta.xml")


class FurutaMJCFVectorEnv(ABDVectorEnv):
    """N Furuta pendulums from an MJCF file, stepped together (see the module docstring)."""

    dt, frame_skip = 0.01, 2  # the file's timestep; 50 Hz control
    render_plane, render_center, render_width = "xz", (0.1, 0.2), 0.8
    theta_threshold = 0.3  # rad

    def build_scene(self):
        return ag.Scene.from_mjcf(MODEL)

    def observation_high(self):
        return np.array([1.0, 1.0, 2 * self.theta_threshold, self.velocity_bound, self.velocity_bound])

    def initial_state(self, n, rng, options):
        return rng.uniform(-0.05, 0.05, size=(n, 2)), rng.uniform(-0.05, 0.05, size=(n, 2))

    def observe(self):
        xp, q, v = self.xp, self.coords(), self.velocities()
        return xp.stack([xp.cos(q[:, 0]), xp.sin(q[:, 0]), q[:, 1], v[:, 0], v[:, 1]], axis=1)

    def reward(self, obs, actions):
        return 1.0 - 0.01 * actions[:, 0] ** 2

    def terminated(self, obs):
        return self.xp.abs(obs[:, 2]) > self.theta_threshold


class FurutaMJCFEnv(ABDEnv):
    """One Furuta pendulum from the MJCF file as a gymnasium.Env."""

    vector_class = FurutaMJCFVectorEnv


def register():
    """Make ``gym.make(ENV_ID)`` and ``gym.make_vec(ENV_ID, n, vectorization_mode="vector_entry_point")`` work."""
    if ENV_ID not in gym.registry:
        gym.register(ENV_ID, entry_point=FurutaMJCFEnv, vector_entry_point=FurutaMJCFVectorEnv, max_episode_steps=200,
                     reward_threshold=190.0)


def check():
    """Gymnasium's and Stable-Baselines3's environment checkers on the single-world env."""
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    check_env(gym.make(ENV_ID).unwrapped)
    sb3_check_env(gym.make(ENV_ID))


def compare_with_mujoco(qpos=(0.0, 0.3), qvel=(1.0, 0.0), seconds=1.0, dt=0.002):
    """Largest |qpos difference| [rad] over ``seconds`` of unactuated motion from (qpos, qvel):
    abd_gym (float64, step ``dt``) against MuJoCo itself (RK4 at a 1e-4 s step, the reference)."""
    return mjcf.compare_with_mujoco(MODEL, (qpos, qvel), seconds, dt).max_error


CONFIG = {  # the keys of a configs/*.yaml file
    "env_id": ENV_ID,
    "algo": "ppo",
    "n_envs": 16,
    "n_timesteps": 100_000,
    "eval_episodes": 10,
    "hyperparams": {"n_steps": 64, "batch_size": 256, "gamma": 0.98, "learning_rate": 1e-3},
    "policy_kwargs": {"net_arch": [64, 64]},
}


def train(run_dir="runs/furuta_mjcf", **overrides):
    """Train PPO with abd_gym.agents; returns the run's summary (also in ``run_dir/summary.json``)."""
    from abd_gym.agents.train import train as train_config

    return train_config(dict(CONFIG, **overrides), config_name="furuta_mjcf_ppo", run_dir=run_dir, progress_bar=False)


if __name__ == "__main__":
    print(f"largest difference from MuJoCo over 1 s: {compare_with_mujoco():.1e} rad")
    register()
    check()
    summary = train()
    print(f"return {summary['mean_return']:.1f} ± {summary['std_return']:.1f} in {summary['run_dir']}")
