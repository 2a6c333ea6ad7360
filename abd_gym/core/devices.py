"""Which Warp devices exist here, and a device name checked against them.

A device that does not exist is a ``ValueError`` naming the ones that do, e.g.
``device 'cuda:0' is not available; available: cpu``, raised before anything is allocated.
"""
from __future__ import annotations

import warp as wp


def available_devices() -> list[str]:
    """The names of the devices Warp can use here, e.g. ``["cpu", "cuda:0"]``."""
    return [str(d) for d in wp.get_devices()]


def resolve_device(device=None) -> wp.Device:
    """The Warp device named ``device`` ("cpu", "cuda", "cuda:N", a ``wp.Device`` or None for
    Warp's default).  ``ValueError`` if there is no such device here."""
    if device is None or isinstance(device, wp.Device):
        return wp.get_device(device)
    names = available_devices()
    name = str(device)
    # "cuda" is Warp's alias of the current CUDA device
    if name in names or (name == "cuda" and any(n.startswith("cuda") for n in names)):
        return wp.get_device(name)
    raise ValueError(f"device {name!r} is not available; available: {', '.join(names)}")
