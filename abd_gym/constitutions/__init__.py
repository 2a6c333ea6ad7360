"""One module per constitution: its formula (docstring), float64 NumPy reference and Warp kernel.

``REGISTRY`` lists the modules; a scene compiles only the ones it uses.
"""
from . import affine_body, drive, fixed_joint, prismatic_joint, prismatic_limit, revolute_joint, revolute_limit

REGISTRY = (affine_body, revolute_joint, prismatic_joint, fixed_joint, revolute_limit, prismatic_limit, drive)
