"""A function of fixed-address tensors, replayed from a CUDA graph after a few eager calls."""
from __future__ import annotations

from collections.abc import Callable

import torch as th

__all__ = ["GraphedCall"]


class GraphedCall:
    """``fn()`` run eagerly ``warmup`` times on a side stream, then captured once on that stream and
    replayed (the capture records without running, so the call that captures replays too).

    ``fn`` takes no arguments and must read and write only tensors that keep their addresses
    between calls (inputs are copied into them before a call, outputs read after), must not read
    anything back to the host, and must launch the same kernels every call.  The eager calls create
    what is made lazily on first use (cuBLAS handles, an optimiser's state) outside the capture, as
    PyTorch's capture requires.  ``capture`` False (a CPU device): every call is eager.
    """

    def __init__(self, fn: Callable[[], None], device: th.device, *, warmup: int = 1, capture: bool | None = None):
        self.fn = fn
        self.device = device
        self.capture = device.type == "cuda" if capture is None else capture
        self.warmup = warmup
        self.graph: th.cuda.CUDAGraph | None = None
        self._calls = 0
        self._stream = th.cuda.Stream(device) if self.capture else None

    def __call__(self) -> None:
        if not self.capture:
            self.fn()
        elif self.graph is not None:
            self.graph.replay()
        else:
            current = th.cuda.current_stream(self.device)
            self._stream.wait_stream(current)
            if self._calls < self.warmup:
                with th.cuda.stream(self._stream):
                    self.fn()
            else:
                graph = th.cuda.CUDAGraph()
                with th.cuda.graph(graph, stream=self._stream):
                    self.fn()
                self.graph = graph
            current.wait_stream(self._stream)
            if self.graph is not None:
                self.graph.replay()
        self._calls += 1

    def reset(self) -> None:
        """Forget the graph (the tensors ``fn`` reads moved): the next call runs eagerly and captures again."""
        self.graph = None
        self._calls = 0
