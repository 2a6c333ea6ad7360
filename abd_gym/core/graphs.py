"""Graph capture, in one place: Warp's graphs, Torch's, and one nested in the other.

* :func:`capture`: the launches of ``fn()`` as a Warp graph (a CUDA graph on a GPU, Warp's
  command replay on the CPU), its kernels already loaded (``force_module_load=False``: a module
  load is no graph node).  The simulator's step and the vector env's step graph use it.
* :func:`capture_torch`: ``fn()``'s Torch operations and Warp launches as one Torch CUDA graph
  (Torch's capture on a side stream, Warp's launches on the same stream, told the capture is
  external).
* :func:`insert_child_graph`: a Torch graph nested as a child node of a Warp capture, so that a
  step whose Warp and Torch parts are two captures is still one graph launch.
"""
from __future__ import annotations

import ctypes

import warp as wp


def capture(device, fn):
    """``fn()`` captured on ``device``'s current stream: returns (the Warp graph, what fn returned)."""
    with wp.ScopedCapture(device=device, force_module_load=False) as scoped:
        result = fn()
    return scoped.graph, result


def capture_torch(torch_device, fn, keep: bool = False):
    """A Torch CUDA graph of ``fn()`` on ``torch_device`` and fn's outputs: Torch's capture on a
    side stream, Warp's launches on the same stream (an external capture to Warp).  ``keep``: the
    graph keeps its CUDA graph (``raw_cuda_graph``), for nesting in another
    (:func:`insert_child_graph`), and is instantiated only if replayed."""
    import torch

    graph = torch.cuda.CUDAGraph(keep_graph=True) if keep else torch.cuda.CUDAGraph()
    stream = torch.cuda.Stream(device=torch_device)
    stream.wait_stream(torch.cuda.current_stream(torch_device))
    ws = wp.stream_from_torch(stream)
    with torch.cuda.graph(graph, stream=stream, capture_error_mode="thread_local"):
        with wp.ScopedStream(ws, sync_enter=False):
            wp.capture_begin(stream=ws, external=True)
            try:
                outputs = fn()
            finally:
                wp.capture_end(stream=ws)
    torch.cuda.current_stream(torch_device).wait_stream(stream)
    return graph, outputs


def insert_child_graph(device, raw) -> bool:
    """Add the CUDA graph ``raw`` (a cudaGraph_t, e.g. a kept Torch graph's ``raw_cuda_graph()``)
    as a child node of the Warp capture under way on ``device``'s current stream.

    Warp has no public call for it: this is the native call Warp's own ``capture_if`` makes for a
    ``Graph`` branch (``wp_cuda_graph_insert_child_graph`` of Warp's runtime, internal to Warp).
    Returns False where this Warp lacks it or the call fails; the caller then replays the child
    graph on its own after the capture's graph (the same work, one graph launch more)."""
    try:
        from warp._src.context import runtime

        insert = runtime.core.wp_cuda_graph_insert_child_graph
    except (ImportError, AttributeError):
        return False
    return bool(insert(device.context, device.stream.cuda_stream, ctypes.c_void_p(raw)))
