"""Kernel launches recorded once and replayed with only their changed arguments.

Packing a launch's arguments is host work that a small batch notices: a reset's restart kernels
take ~40 arguments, most of them the same arrays every time, and packing them cost more than the
kernels themselves on the CPU.  A recorded command keeps the packed arguments; a replay sets only
those that changed (by identity; Python scalars by value) and the launch's dim.

On the CPU even a recorded command packs every argument again at each launch (Warp builds the
kernel's argument struct anew), so there a launch is captured as a graph (Warp's CPU command
replay) per set of arguments seen, keyed by the arrays' identities and the other values, and
the graph is replayed: a one-world reset's restart launch then costs a graph launch.  A graph
keeps its arguments alive, so an identity in its key cannot be another array's.
"""
from __future__ import annotations

import warp as wp

from . import graphs

# argument sets whose CPU graphs one recorded launch keeps (a staging buffer's two slots, a few
# batch sizes); past it they are dropped and captured again as they come
MAX_CPU_GRAPHS = 16


def replay(recorded: dict, key, kernel, dim, inputs: list, device) -> None:
    """Launch ``kernel`` over ``dim`` with ``inputs`` on ``device`` as the command ``recorded[key]``:
    recorded (``wp.launch(..., record_cmd=True)``) on the key's first call, replayed after it; on
    the CPU, outside a capture, as the graph of these arguments from the second call on."""
    entry = recorded.get(key)
    if entry is None:
        cmd = wp.launch(kernel, dim=dim, inputs=inputs, device=device, record_cmd=True)
        # on the CPU: the graphs by arguments, and where the arguments that are not arrays stand
        cpu = ({}, [i for i, a in enumerate(inputs) if not isinstance(a, wp.array)]) if cmd.device.is_cpu else None
        recorded[key] = (cmd, list(inputs), cpu)
        cmd.launch()
        return
    cmd, old, cpu = entry
    if cpu is not None and not cmd.device.is_capturing:
        _replay_cpu(*cpu, kernel, dim, inputs, cmd.device)
        return
    for i, (a, b) in enumerate(zip(inputs, old)):
        if a is not b and not (isinstance(a, (int, float)) and a == b):
            cmd.set_param_at_index(i, a)
            old[i] = a
    cmd.set_dim(dim)
    cmd.launch()


def _replay_cpu(cpu_graphs: dict, values: list, kernel, dim, inputs: list, device) -> None:
    """The launch as the graph of its arguments (captured on first sight; the kernel is loaded):
    keyed by the dim, each argument's identity and, at the positions ``values``, its value."""
    key = [dim, *map(id, inputs)]
    for i in values:
        key[i + 1] = inputs[i]
    signature = tuple(key)
    entry = cpu_graphs.get(signature)
    if entry is None:
        if len(cpu_graphs) >= MAX_CPU_GRAPHS:
            cpu_graphs.clear()
        args = list(inputs)  # kept with the graph: the identities in its signature stay these arrays'
        graph, _ = graphs.capture(device, lambda: wp.launch(kernel, dim=dim, inputs=args, device=device))
        entry = cpu_graphs[signature] = (graph, args)
    wp.capture_launch(entry[0])
