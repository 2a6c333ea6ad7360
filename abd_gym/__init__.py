"""abd_gym: batched affine-body dynamics with joint and limit constitutions, on Warp.

The tasks live in ``abd_gym.envs`` and the Stable-Baselines3 training in ``abd_gym.agents``;
neither is imported here (the Gymnasium ids below name their classes by string).  Warp's
per-module load lines are off while abd_gym is used as a library (:mod:`abd_gym.warp_log` says
how to turn them back on).
"""
from .warp_log import quiet_warp

quiet_warp()  # before any kernel module loads

from .plan import ExecutionPlan
from .scene import Scene
from .shapes import Box, Capsule, Cylinder, Inertia, Sphere
from .simulator import Simulator
from .status import WorldStatus
from .registration import register_envs

register_envs()  # the abd_gym/ Gymnasium ids (entry points load lazily from abd_gym.envs)

__all__ = ["Scene", "Simulator", "ExecutionPlan", "Box", "Sphere", "Capsule", "Cylinder", "Inertia", "WorldStatus"]
__version__ = "0.1.0"
