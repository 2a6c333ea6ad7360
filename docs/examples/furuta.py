"""Furuta pendulum: balance a pendulum on the tip of an arm that a motor turns about the vertical.

Scene (gravity −z; zero pose = arm along +x, pendulum upright): a fixed base; an arm (0.1 kg,
0.2 m) on the motor hinge about +z; a pendulum (0.05 kg, 0.3 m) on a hinge about the arm's axis
(+x in the zero pose) at the arm's tip.  An effort drive on the motor, |τ| ≤ 0.3 N·m.
Action: Box(-1, 1, (1,)): the motor torque a × 0.3 N·m.
Observation: [cos φ, sin φ, θ, φ̇, θ̇] (arm angle φ, pendulum angle θ [rad], rates [rad/s]).
Reward: 1 per step − 0.01·a².  Termination: |θ| > 0.3 rad.  Truncation: 200 steps (4 s).
Reset: φ, θ, φ̇, θ̇ ~ U(−0.05, 0.05).
"""
import gymnasium as gym
import numpy as np

import abd_gym as ag
from abd_gym.vector.vector_env import ABDEnv, ABDVectorEnv

ENV_ID = "abd_gym_examples/Furuta-v0"


class FurutaVectorEnv(ABDVectorEnv):
    """N Furuta pendulums stepped together (see the module docstring)."""

    dt, frame_skip = 0.01, 2  # 100 Hz physics, 50 Hz control
    render_plane, render_center, render_width = "xz", (0.1, 0.2), 0.8
    theta_threshold = 0.3  # rad

    def __init__(self, num_envs=1, *, arm_length=0.2, pendulum_length=0.3, max_torque=0.3, **kwargs):
        # the task's own arguments first: the base's __init__ calls build_scene
        self.arm_length, self.pendulum_length, self.max_torque = arm_length, pendulum_length, max_torque
        super().__init__(num_envs, **kwargs)

    def build_scene(self):
        a, p, h = self.arm_length, self.pendulum_length, 0.1  # h: the arm's height [m]
        scene = ag.Scene(gravity=(0.0, 0.0, -9.81))
        base = scene.add_body(ag.Cylinder(radius=0.03, half_height=h / 2), mass=1.0, position=(0, 0, h / 2),
                              fixed=True, name="base")
        arm = scene.add_body(ag.Box(half_extents=(a / 2, 0.01, 0.01)), mass=0.1, position=(a / 2, 0, h), name="arm")
        pendulum = scene.add_body(ag.Box(half_extents=(0.01, 0.01, p / 2)), mass=0.05, position=(a, 0, h + p / 2),
                                  name="pendulum")
        motor = scene.add_revolute_joint(base, arm, anchor=(0, 0, h), axis=(0, 0, 1), name="motor")
        scene.add_revolute_joint(arm, pendulum, anchor=(a, 0, h), axis=(1, 0, 0), name="pivot")
        scene.add_drive(motor, mode="effort", max_effort=self.max_torque)
        return scene

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


class FurutaEnv(ABDEnv):
    """One Furuta pendulum as a gymnasium.Env."""

    vector_class = FurutaVectorEnv


def register():
    """Make ``gym.make(ENV_ID)`` and ``gym.make_vec(ENV_ID, n, vectorization_mode="vector_entry_point")`` work."""
    if ENV_ID not in gym.registry:
        gym.register(ENV_ID, entry_point=FurutaEnv, vector_entry_point=FurutaVectorEnv, max_episode_steps=200)


def check():
    """Gymnasium's and Stable-Baselines3's environment checkers on the single-world env."""
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    check_env(gym.make(ENV_ID).unwrapped)
    sb3_check_env(gym.make(ENV_ID))


CONFIG = {  # the keys of a configs/*.yaml file
    "env_id": ENV_ID,
    "algo": "ppo",
    "n_envs": 8,
    "n_timesteps": 20_000,
    "eval_episodes": 8,
    "hyperparams": {"n_steps": 64, "batch_size": 128, "gamma": 0.98, "learning_rate": 1e-3},
    "policy_kwargs": {"net_arch": [64, 64]},
}


def train(run_dir="runs/furuta", **overrides):
    """Train PPO with abd_gym.agents; returns the run's summary (also in ``run_dir/summary.json``)."""
    from abd_gym.agents.train import train as train_config

    return train_config(dict(CONFIG, **overrides), config_name="furuta_ppo", run_dir=run_dir, progress_bar=False)


if __name__ == "__main__":
    register()
    check()
    summary = train()
    print(f"return {summary['mean_return']:.1f} ± {summary['std_return']:.1f} in {summary['run_dir']}")
