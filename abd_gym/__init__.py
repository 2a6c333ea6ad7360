"""abd_gym: batched affine-body dynamics with joint and limit constitutions, on Warp.

The tasks live in ``abd_gym.envs`` and the Stable-Baselines3 training in ``abd_gym.agents``;
neither is imported here (the Gymnasium ids below name their classes by string).  Warp's
per-module load lines are off while abd_gym is used as a library (:mod:`abd_gym.core.warp_log` says
how to turn them back on).
"""
from .core.warp_log import quiet_warp

quiet_warp()  # before any kernel module loads

from .solver.plan import ExecutionPlan
from .sim.scene import Scene
from .sim.shapes import Box, Capsule, Cylinder, Inertia, Sphere
from .sim.simulator import Simulator
from .sim.status import WorldStatus
from .vector.registration import register_envs

register_envs()  # the abd_gym/ Gymnasium ids (entry points load lazily from abd_gym.envs)

__all__ = ["Scene", "Simulator", "ExecutionPlan", "Box", "Sphere", "Capsule", "Cylinder", "Inertia", "WorldStatus"]
__version__ = "0.1.0"
