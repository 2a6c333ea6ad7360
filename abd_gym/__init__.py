"""abd_gym: batched affine-body dynamics with joint and limit constitutions, on Warp."""
from .plan import ExecutionPlan
from .scene import Scene
from .shapes import Box, Capsule, Cylinder, Inertia, Sphere
from .simulator import Simulator
from .registration import register_envs

register_envs()  # the abd_gym/ Gymnasium ids (entry points load lazily from envs/)

__all__ = ["Scene", "Simulator", "ExecutionPlan", "Box", "Sphere", "Capsule", "Cylinder", "Inertia"]
__version__ = "0.1.0"
