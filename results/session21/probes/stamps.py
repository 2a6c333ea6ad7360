import numpy as np
import warp as wp

"""The probes' stamp kernels, on abd_gym.timestamps' global timer (the pair form for envstamp.py)."""
from abd_gym.timestamps import global_timer as gtimer
from abd_gym.timestamps import stamp as stamp1  # noqa: F401 -- a ring's next slot (envparts.py, envstamp2.py)


@wp.kernel
def stamp(t: wp.array(dtype=wp.uint64), counter: wp.array(dtype=wp.int32), which: int):
    """Pair i's stamp ``which`` (0 before, 1 after: the pair counted)."""
    i = counter[0]
    if 2 * i + 1 < t.shape[0]:
        t[2 * i + which] = gtimer()
    if which == 1:
        counter[0] = i + 1


class Clock:
    """Named stamp points, each with its own ring."""

    def __init__(self, names, n=4096, device="cuda:0"):
        self.names = names
        self.t = {k: wp.zeros(n, dtype=wp.uint64, device=device) for k in names}
        self.c = {k: wp.zeros(1, dtype=wp.int32, device=device) for k in names}
        self.device = device

    def stamp(self, name):
        wp.launch(stamp1, dim=1, inputs=[self.t[name], self.c[name]], device=self.device)

    def table(self, last):
        wp.synchronize()
        out = {}
        for k in self.names:
            n = int(self.c[k].numpy()[0])
            out[k] = self.t[k].numpy()[n - last: n].astype(np.int64)
        return out
