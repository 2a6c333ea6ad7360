"""Device timestamps that a CUDA graph can hold: for timing a part of a captured step.

CUDA events cannot be recorded inside a graph that is replayed, and events around a part launched
op by op also time the gaps in which the device waits for the host's next launch.  Here a
one-thread kernel writes the
GPU's global timer (``%globaltimer``, ns) to the next slot of a ring; a captured launch writes the
next slot at each replay.  On the CPU the stamp is 0: time the host there.
"""

import numpy as np
import warp as wp


@wp.func_native("""
unsigned long long t = 0;
#if defined(__CUDA_ARCH__)
asm volatile("mov.u64 %0, %%globaltimer;" : "=l"(t));
#endif
return t;
""")
def global_timer() -> wp.uint64:
    """The GPU's global timer [ns] (0 on the CPU)."""
    ...


@wp.kernel
def stamp(ring: wp.array(dtype=wp.uint64), count: wp.array(dtype=wp.int32)):
    """The timer into ring[count] (while it fits), and one more counted."""
    i = count[0]
    if i < ring.shape[0]:
        ring[i] = global_timer()
    count[0] = i + 1


class Stamps:
    """A ring of timestamps on ``device``; ``mark()`` launches a stamp (on the current stream, so a
    capture holds it), ``read()`` returns the stamps written so far [ns], int64."""

    def __init__(self, device, size: int):
        self.device = wp.get_device(device)
        self.ring = wp.zeros(int(size), dtype=wp.uint64, device=self.device)
        self.count = wp.zeros(1, dtype=wp.int32, device=self.device)

    def mark(self):
        wp.launch(stamp, dim=1, inputs=[self.ring, self.count], device=self.device)

    def clear(self):
        """An empty ring, once the device has cleared it (a graph replayed on another stream next
        must not race the clear)."""
        self.count.zero_()
        wp.synchronize_device(self.device)

    def read(self) -> np.ndarray:
        n = int(self.count.numpy()[0])
        if n > self.ring.shape[0]:
            raise RuntimeError(f"{n} stamps overflowed a ring of {self.ring.shape[0]}")
        return self.ring.numpy()[:n].astype(np.int64)
