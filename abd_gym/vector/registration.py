"""Gymnasium registration of the abd_gym tasks under the ``abd_gym/`` namespace.

Importing ``abd_gym`` registers every task; ids, creators and limits:

=================================  ===========================================  =====  =========
id                                 module (single env / vector env)             steps  threshold
=================================  ===========================================  =====  =========
abd_gym/Pendulum-v0                abd_gym.envs.pendulum                        200    -200
abd_gym/CartPole-v0                abd_gym.envs.cartpole                        500    475
abd_gym/CartPoleSwingUp-v0         abd_gym.envs.cartpole_swingup                500    350
abd_gym/DoublePendulumCart-v0      abd_gym.envs.double_pendulum_cart            500    450
abd_gym/Acrobot-v0                 abd_gym.envs.acrobot                         500    -100
abd_gym/TwoLinkReacher-v0          abd_gym.envs.reacher                         50     -5
abd_gym/FourBar-v0                 abd_gym.envs.fourbar                         200    150
abd_gym/SliderCrank-v0             abd_gym.envs.slider_crank                    200    150
abd_gym/InvertedPendulum-v5        abd_gym.envs.inverted_pendulum               1000   950
abd_gym/InvertedDoublePendulum-v5  abd_gym.envs.inverted_double_pendulum        1000   9100
abd_gym/Reacher-v5                 abd_gym.envs.reacher_v5                      50     -3.75
abd_gym/ArmReach-v0                abd_gym.envs.arm_reach                       50     -15
=================================  ===========================================  =====  =========

The ``-v5`` tasks are Gymnasium's MuJoCo classics built from Gymnasium's own model files (they
need the ``mujoco`` package); each module's docstring says what differs from Gymnasium's env.

    env = gym.make("abd_gym/CartPole-v0")                          # one world, CPU, TimeLimit
    envs = gym.make_vec("abd_gym/CartPole-v0", num_envs=4096,      # native batched env
                        vectorization_mode="vector_entry_point", device="cuda:0", backend="torch")

Entry points are strings, so nothing under ``abd_gym.envs`` is imported until an env is made.

Former ids (``RENAMED``) stay registered for one release: making one makes the task under its
new id, with a one-line ``FutureWarning`` naming it.  ``abd_gym/Reacher-v0`` is now
``abd_gym/TwoLinkReacher-v0``: beside ``abd_gym/Reacher-v5`` Gymnasium read it as an older
version of that task, which it is not, and warned on every make that it was out of date.
"""
from __future__ import annotations

import importlib
import warnings

import gymnasium as gym

NAMESPACE = "abd_gym"

# name: (module, single-env class, vector-env class, max_episode_steps, reward_threshold)
TASKS = {
    "Pendulum-v0": ("abd_gym.envs.pendulum", "PendulumEnv", "PendulumVectorEnv", 200, -200.0),
    "CartPole-v0": ("abd_gym.envs.cartpole", "CartPoleEnv", "CartPoleVectorEnv", 500, 475.0),
    "CartPoleSwingUp-v0": ("abd_gym.envs.cartpole_swingup", "CartPoleSwingUpEnv", "CartPoleSwingUpVectorEnv", 500, 350.0),
    "DoublePendulumCart-v0": ("abd_gym.envs.double_pendulum_cart", "DoublePendulumCartEnv", "DoublePendulumCartVectorEnv",
                              500, 450.0),
    "Acrobot-v0": ("abd_gym.envs.acrobot", "AcrobotEnv", "AcrobotVectorEnv", 500, -100.0),
    "TwoLinkReacher-v0": ("abd_gym.envs.reacher", "ReacherEnv", "ReacherVectorEnv", 50, -5.0),
    "FourBar-v0": ("abd_gym.envs.fourbar", "FourBarEnv", "FourBarVectorEnv", 200, 150.0),
    "SliderCrank-v0": ("abd_gym.envs.slider_crank", "SliderCrankEnv", "SliderCrankVectorEnv", 200, 150.0),
    "InvertedPendulum-v5": ("abd_gym.envs.inverted_pendulum", "InvertedPendulumEnv", "InvertedPendulumVectorEnv",
                            1000, 950.0),
    "InvertedDoublePendulum-v5": ("abd_gym.envs.inverted_double_pendulum", "InvertedDoublePendulumEnv",
                                  "InvertedDoublePendulumVectorEnv", 1000, 9100.0),
    "Reacher-v5": ("abd_gym.envs.reacher_v5", "ReacherV5Env", "ReacherV5VectorEnv", 50, -3.75),
    "ArmReach-v0": ("abd_gym.envs.arm_reach", "ArmReachEnv", "ArmReachVectorEnv", 50, -15.0),
}  # fmt: skip


# former id: the task's id now (each former id registered for one more release)
RENAMED = {"Reacher-v0": "TwoLinkReacher-v0"}


class FormerId:
    """Entry point (``vector``: vector entry point) of a former id: warns once in a line, then makes
    the task under its new id."""

    def __init__(self, old: str, new: str, vector: bool = False):
        self.old, self.new, self.vector = old, new, vector

    def __call__(self, **kwargs):
        warnings.warn(f"{NAMESPACE}/{self.old} is now {NAMESPACE}/{self.new}; the former id goes in the next release",
                      FutureWarning, stacklevel=2)  # fmt: skip
        module, single, vector = TASKS[self.new][:3]
        return getattr(importlib.import_module(module), vector if self.vector else single)(**kwargs)


def env_ids() -> list[str]:
    """Every registered abd_gym id, e.g. ``"abd_gym/CartPole-v0"``."""
    return [f"{NAMESPACE}/{name}" for name in TASKS]


def register_envs() -> None:
    """Register every task (idempotent: ids already in the registry are left as they are)."""
    for name, (module, single, vector, steps, threshold) in TASKS.items():
        env_id = f"{NAMESPACE}/{name}"
        if env_id in gym.registry:
            continue
        gym.register(
            id=env_id,
            entry_point=f"{module}:{single}",
            vector_entry_point=f"{module}:{vector}",
            max_episode_steps=steps,
            reward_threshold=threshold,
        )
    for old, new in RENAMED.items():
        env_id = f"{NAMESPACE}/{old}"
        # Gymnasium's "out of date, upgrade to v5" for a former id whose name a newer task shares
        warnings.filterwarnings("ignore", message=rf".*The environment {env_id} is out of date")
        if env_id in gym.registry:
            continue
        _, _, _, steps, threshold = TASKS[new]
        gym.register(id=env_id, entry_point=FormerId(old, new), vector_entry_point=FormerId(old, new, vector=True),
                     max_episode_steps=steps, reward_threshold=threshold)  # fmt: skip
