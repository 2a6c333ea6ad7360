"""MuJoCo's models in and out: MJCF and URDF files as scenes (``importer``, through MuJoCo's
compiler) and a scene as an equivalent MJCF model (``export``)."""
from .export import MjcfExport, spanning_tree, to_mjcf
from .importer import MjcfInfo, build, load

__all__ = ["MjcfInfo", "load", "build", "MjcfExport", "spanning_tree", "to_mjcf"]
