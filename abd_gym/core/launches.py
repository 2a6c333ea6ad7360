"""Kernel launches recorded once and replayed with only their changed arguments.

Packing a launch's arguments is host work that a small batch notices: a reset's restart kernels
take ~40 arguments, most of them the same arrays every time, and packing them cost more than the
kernels themselves on the CPU.  A recorded command keeps the packed arguments; a replay sets only
those that changed (by identity; Python scalars by value) and the launch's dim.
"""
from __future__ import annotations

import warp as wp


def replay(recorded: dict, key, kernel, dim, inputs: list, device) -> None:
    """Launch ``kernel`` over ``dim`` with ``inputs`` on ``device`` as the command ``recorded[key]``:
    recorded (``wp.launch(..., record_cmd=True)``) on the key's first call, replayed after it."""
    entry = recorded.get(key)
    if entry is None:
        cmd = wp.launch(kernel, dim=dim, inputs=inputs, device=device, record_cmd=True)
        recorded[key] = (cmd, list(inputs))
    else:
        cmd, old = entry
        for i, (a, b) in enumerate(zip(inputs, old)):
            if a is not b and not (isinstance(a, (int, float)) and a == b):
                cmd.set_param_at_index(i, a)
                old[i] = a
        cmd.set_dim(dim)
    cmd.launch()
