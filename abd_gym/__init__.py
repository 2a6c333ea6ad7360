"""abd_gym: batched affine-body dynamics with joint and limit constitutions, on Warp."""
from .scene import Scene
from .shapes import Box, Capsule, Cylinder, Inertia, Sphere
from .simulator import Simulator
from .registration import register_envs

register_envs()  # the abd_gym/ Gymnasium ids (entry points load lazily from abd_gym.envs)

__all__ = ["Scene", "Simulator", "Box", "Sphere", "Capsule", "Cylinder", "Inertia"]
__version__ = "0.1.0"
