"""A failed step retried as substeps: a world whose step did not converge or broke down
(status.UNCONVERGED, BREAKDOWN) takes that step again as 2 steps of dt/2, then, if one of those
fails, as 4 of dt/4, from the state it had before the step; only then is it rejected (its status
stays, its state is the one before the step).

Only the retried worlds step again: the substeps are the one-launch fused step (a Solver of
dt/2 or dt/4 on the same model and state) holding every other world, whose rows it neither reads
nor writes, so a batch whose worlds all converge steps exactly as without retries.  A step costs
the healthy batch one launch (``mark``: which worlds failed, and a device flag) and a conditional
branch (``wp.capture_if``) that a graph holds; on the CPU, a look at the status and substeps in
host memory, with the launch only where a world is not OK or the last step was retried.  The
substep solvers and the copy of the retried worlds' state they start from are made at the first
retry on the CPU, at the first step on a GPU (so that the graphs captured after it hold the
branch); their kernel is the one-launch step built to hold worlds, compiled once per scene.

A retried world's next step is an implicit Euler step (fresh RESET): its BDF2 history spans a
substep, not dt.  ``state.substeps[w]``: the substeps of world w's last step (1, 2 or 4).

With the energy test (``energy``, an energy_gain.EnergyCheck: a conservative scene, built with
SolverSettings.energy_gain > 0) a step that converged but gained more energy than the test allows
is retried the same way, from the state before the step, which ``before`` copies at the start of
every step (the state a converged step leaves is the one after it); an attempt that converges and
still gains is taken again at the next count, and at 4 substeps it is kept and flagged
(``state.gained``).  A scene without the test runs none of this.
"""

import functools

import numpy as np
import warp as wp

from ..core import graphs
from ..sim.status import BREAKDOWN, OK, UNCONVERGED
from .kernels import RESET, RESTART, next_attempt

SUBSTEPS = (2, 4)
# the state's arrays a retry leaves as its last attempt wrote them (the rest are put back to the
# state before the step where an attempt fails): the status and the last solve's counters
KEPT = ("status", "fresh", "substeps", "iterations", "factorizations", "converged", "retried", "gained")


@wp.kernel
def mark(status: wp.array(dtype=wp.int32), iterations: wp.array(dtype=wp.int32), fresh: wp.array(dtype=wp.int32),
         substeps: wp.array(dtype=wp.int32), hold: wp.array(dtype=wp.int32), go: wp.array(dtype=wp.int32),
         idle: wp.array(dtype=wp.int32), flag: wp.array(dtype=wp.int32)):  # fmt: skip
    """After a step: a world this step solved (not held: hold[w] == 0 and go[0] != 0; iterations >
    0) and rejected is to be retried (idle 0, status OK again, an implicit Euler start, 2
    substeps; flag[0] = 1); every other world idles (1), and a world stepped OK took 1 step."""
    w = wp.tid()
    idle[w] = 1
    if go[0] == 0 or hold[w] != 0:
        return
    s = status[w]
    if s == OK:
        substeps[w] = 1
    elif (s == UNCONVERGED or s == BREAKDOWN) and iterations[w] > 0:
        idle[w] = 0
        status[w] = OK
        fresh[w] = RESTART
        substeps[w] = 2
        flag[0] = 1


@wp.kernel
def settle(status: wp.array(dtype=wp.int32), fresh: wp.array(dtype=wp.int32), substeps: wp.array(dtype=wp.int32),
           idle: wp.array(dtype=wp.int32), back: wp.array(dtype=wp.int32), n: int, next_n: int):  # fmt: skip
    """After an attempt of ``n`` substeps: a retried world that came through idles from now on (its
    next step an implicit Euler step: RESET); one that failed goes back to the state before the
    step (back 1) and tries ``next_n`` substeps, or, with next_n 0, is rejected (status kept)."""
    w = wp.tid()
    back[w] = 0
    if idle[w] != 0:
        return
    if status[w] == OK:
        idle[w] = 1
        fresh[w] = RESET
        return
    back[w] = 1
    next_attempt(status, fresh, substeps, idle, w, n, next_n)


@functools.lru_cache(maxsize=None)
def _copy_rows(scalar):
    @wp.kernel
    def copy_rows(dst: wp.array2d(dtype=scalar), src: wp.array2d(dtype=scalar), mask: wp.array(dtype=wp.int32),
                  want: int):  # fmt: skip
        """dst[w] = src[w] for the worlds with mask[w] == want."""
        w, i = wp.tid()
        if mask[w] == want:
            dst[w, i] = src[w, i]

    return copy_rows


def _rows(a: wp.array) -> wp.array:
    """A contiguous (W, ...) array as (W, k) of its scalars (a view)."""
    scalar = getattr(a.dtype, "_wp_scalar_type_", a.dtype)
    k = int(np.prod(a.shape[1:], dtype=np.int64)) * int(np.prod(getattr(a.dtype, "_shape_", ()), dtype=np.int64))
    return wp.array(ptr=a.ptr, dtype=scalar, shape=(a.shape[0], k), device=a.device)


class Retry:
    """The retry of one Solver's failed worlds (module docstring)."""

    def __init__(self, solver, make_solver, energy=None):
        """``make_solver(model, dt, settings, plan)``: a Solver of no retry of its own (the substeps');
        ``energy``: the energy test (energy_gain.EnergyCheck) or None."""
        self.solver, self.make_solver, self.energy = solver, make_solver, energy
        # whether this step runs the energy test (before: on the CPU, not where every world's drive pushes)
        self.testing = energy is not None
        m = solver.model
        W, dev = m.num_worlds, m.device
        self.flag = wp.zeros(1, dtype=wp.int32, device=dev)
        self.idle = wp.ones(W, dtype=wp.int32, device=dev)  # 0: the world is being retried
        self.back = wp.zeros(W, dtype=wp.int32, device=dev)
        self.all_idle = wp.ones(W, dtype=wp.int32, device=dev)  # (prepare's launch that changes no world)
        self._subs = None  # the substep solvers, SUBSTEPS[i] steps of dt/SUBSTEPS[i] each
        self._pairs = None  # [(state rows, saved rows)] of the arrays an attempt puts back
        self._cpu = wp.get_device(dev).is_cpu
        self._host = None  # CPU: (state, NumPy views of its status and substeps, their bytes when all OK)
        self._graphs = {}  # CPU: (state, hold, go) -> (state, hold, go, the graph of _mark)
        self._last_graph = (None, None, None, None, None)  # CPU: the last check's (state, hold, go, testing, graph)
        self._flag_host = None  # CPU: flag as a NumPy view
        self._save_graph = None  # CPU, with the energy test: (state, the graph of _save)

    @property
    def ready(self) -> bool:
        """Whether the substep solvers and the saved state exist (a graph may hold a retry)."""
        return self._subs is not None

    def prepare(self, state):
        """Make the substep solvers (the one-launch fused step, built to hold worlds) and the copy of
        the state, and load their kernels with launches that change no world."""
        if self._subs is not None:
            return
        s, m = self.solver, self.solver.model
        plan = dict(fused=True, one_launch=True, use_graph=False)
        if wp.get_device(m.device).is_cpu:
            plan["cpu_workers"] = 1  # one launch
        subs = [self.make_solver(m, s.dt / n, s.settings, plan) for n in SUBSTEPS]
        none = wp.zeros(1, dtype=wp.int32, device=m.device)  # go 0: no world is stepped
        for sub in subs:
            sub.enable_hold()
            sub.step(state, 1, hold=self.idle, go=none)
        live = [a for name, a in vars(state).items() if isinstance(a, wp.array) and name not in KEPT]
        self._saved = [wp.empty_like(a) for a in live]  # (owns the memory the views below read)
        self._pairs = [(_rows(a), _rows(b)) for a, b in zip(live, self._saved)]
        for dst, src in self._pairs:  # (want 2 matches no world)
            wp.launch(_copy_rows(dst.dtype), dim=dst.shape, inputs=[src, dst, self.back, 2], device=m.device)
        wp.launch(settle, dim=m.num_worlds, inputs=[state.status, state.fresh, state.substeps, self.all_idle, self.back,
                                                    1, 0], device=m.device)  # fmt: skip
        self._subs = subs

    def check(self, state, hold=None, go=None):
        """After a step of the solver (holding the worlds ``hold`` and, while go[0] == 0, every
        world, as Solver.step does): retry the worlds it failed (module docstring).  On a GPU the
        substep solvers are made at the first check, so that a graph captured later holds them."""
        s, m = self.solver, self.solver.model
        if self._cpu and not self.testing:  # host memory: no launch while every world is OK after 1 substep
            host = self._host
            if host is None or host[0] is not state:
                W = m.num_worlds  # every status OK (0) and every substeps 1, compared as bytes
                host = self._host = (state, state.status.numpy(), state.substeps.numpy(),
                                     np.zeros(W, np.int32).tobytes(), np.ones(W, np.int32).tobytes())  # fmt: skip
            if host[1].tobytes() == host[3] and host[2].tobytes() == host[4]:
                return
        elif self._subs is None and not wp.get_device(m.device).is_capturing:
            self.prepare(state)
        hold = s._no_hold if hold is None else hold
        go = s._go_all if go is None else go
        if self._cpu:  # the energy test's launches every step: replayed (packing their arguments costs more)
            last = self._last_graph  # (the same state, hold, go and test as the last step: no key to build)
            if last[0] is state and last[1] is hold and last[2] is go and last[3] == self.testing:
                graph = last[4]
            else:
                key = (id(state), hold.ptr, go.ptr, self.testing)
                if key not in self._graphs:  # the entry keeps state, hold and go alive, so the key stays theirs
                    device = wp.get_device(m.device)
                    self._graphs[key] = (state, hold, go,
                                         graphs.capture(device, lambda: self._mark(state, hold, go))[0])  # fmt: skip
                graph = self._graphs[key][3]
                self._last_graph = (state, hold, go, self.testing, graph)
            wp.capture_launch(graph)
            if self._flag_host is None:
                self._flag_host = self.flag.numpy()  # (a view of host memory)
            if self._flag_host[0]:  # the branch capture_if takes, without its call
                self._retry(state)
            return
        self._mark(state, hold, go)
        wp.capture_if(self.flag, on_true=self._retry, state=state)

    def _mark(self, state, hold, go):
        """The worlds to retry: those the step failed (mark) and, with the energy test, those that gained."""
        m = self.solver.model
        wp.launch(mark, dim=m.num_worlds, inputs=[state.status, state.iterations, state.fresh, state.substeps, hold, go,
                                                  self.idle, self.flag], device=m.device)  # fmt: skip
        if self.testing:
            self.energy.judge(state, hold, go, self.idle, self.flag)

    def before(self, state, hold=None, go=None):
        """Before a step, with the energy test: the state before it (every world's rows, which a
        retry restores; a held world's copy is never read back) and the energy of the worlds
        whose energy before it is not known (none that the step holds: ``hold``, ``go``)."""
        if self._cpu:  # no test where every world's drive pushes (host memory)
            self.testing = self.energy.any_checked(state)
            if not self.testing:
                return
        s = self.solver
        if self._subs is None and not wp.get_device(s.model.device).is_capturing:
            self.prepare(state)
        self.energy.before(state, s._no_hold if hold is None else hold, s._go_all if go is None else go)
        if self._cpu:  # the copies as one replayed graph (a copy each from Python costs more than all of them)
            if self._save_graph is None or self._save_graph[0] is not state:
                self._save_graph = (state, graphs.capture(wp.get_device(s.model.device), self._save)[0])
            wp.capture_launch(self._save_graph[1])
            return
        self._save()

    def _save(self):
        """The state before the step: every array a retry puts back, copied whole."""
        for live, saved in self._pairs:
            wp.copy(saved, live)

    def _retry(self, state):
        self.prepare(state)
        m = self.solver.model
        for live, saved in self._pairs:  # the retried worlds' state before the step: kept, or (energy) put back
            pair = [live, saved] if self.testing else [saved, live]
            wp.launch(_copy_rows(live.dtype), dim=live.shape, inputs=pair + [self.idle, 0], device=m.device)
        for i, (n, sub) in enumerate(zip(SUBSTEPS, self._subs)):
            sub.step(state, n, hold=self.idle)
            next_n = SUBSTEPS[i + 1] if i + 1 < len(SUBSTEPS) else 0
            if self.testing:
                self.energy.settle(state, self.idle, self.back, n, next_n)
            else:
                wp.launch(settle, dim=m.num_worlds, inputs=[state.status, state.fresh, state.substeps, self.idle,
                                                            self.back, n, next_n], device=m.device)  # fmt: skip
            for live, saved in self._pairs:  # a failed attempt's worlds back to the state before the step
                wp.launch(_copy_rows(live.dtype), dim=live.shape, inputs=[live, saved, self.back, 1], device=m.device)
        self.flag.zero_()
