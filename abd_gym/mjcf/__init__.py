"""MuJoCo's models in and out: MJCF and URDF files as scenes (``importer``, through MuJoCo's
compiler), an imported model's motion against MuJoCo's (``compare``) and a scene as an
equivalent MJCF model (``export``)."""
from .compare import MujocoComparison, compare_with_mujoco
from .export import MjcfExport, spanning_tree, to_mjcf
from .importer import MjcfInfo, build, load

__all__ = ["MjcfInfo", "load", "build", "compare_with_mujoco", "MujocoComparison", "MjcfExport", "spanning_tree",
           "to_mjcf"]
