"""One module per constitution: its formula (docstring), float64 NumPy reference, Warp evaluators
and its declaration, ``CONSTITUTION`` (``protocol.Constitution``).

``REGISTRY`` lists the declarations, in the staged step's order (its energy columns); a scene
compiles only the ones it uses.  A coordinate term (a limit, a drive) is folded into its joint's
fused term after the ones before it here.
"""
from . import (affine_body, drive, fixed_joint, passive, prismatic_joint, prismatic_limit, revolute_joint,
               revolute_limit)
from .protocol import BODY, COORDINATE, JOINT, Constitution

REGISTRY = tuple(m.CONSTITUTION for m in (affine_body, revolute_joint, prismatic_joint, fixed_joint, revolute_limit,
                                          prismatic_limit, drive, passive))  # fmt: skip

__all__ = ["BODY", "COORDINATE", "JOINT", "REGISTRY", "Constitution"]
