"""The vector env's per-step bookkeeping on the device as two Warp kernels (the device path of
``vector_env`` with Torch); the episode clocks tick in the autoreset's first launch (autoreset.py).

Each does the work of a run of one-line Torch operations in one launch: beside the physics, an
env step's cost is its launches, not their arithmetic.  One thread per world.

``mailed`` variants serve the step graph, whose kernel arguments are fixed at capture: they find
the caller's action batch and the step's fresh output buffer by pointers the host writes, before
each replay, into ``mail[slot]`` (page-locked host memory, which a kernel reads directly under
CUDA's unified addressing), and write the done and bad rows straight to page-locked host memory
(``host_flags[slot]``), so that a step is the graph alone: no copy of the actions in, of the
outputs out or of the flags to the host as stream operations of their own.  ``slot`` alternates
between two graphs: the host reads step t's flags while step t + 1 (the other slot) runs.  A
kernel's read of host memory lasts a PCIe round trip (a write there does not wait): so the
check, the step's first kernel, reads the mailbox and copies its slot to device memory, where
the step's last kernel reads the output's pointer.
"""
import functools

import warp as wp


@functools.lru_cache(maxsize=None)
def check_actions(control_dtype, scaled: bool, mailed: bool = False):
    """The kernel that checks, clips and (with ``scaled``) scales world w's actions."""

    @wp.kernel(module="unique")  # a variant made later must not reload the others (in a graph)
    def check(a: wp.array2d(dtype=wp.float32), scale: wp.array(dtype=wp.float32), bound: wp.float32,
              bad: wp.array(dtype=wp.bool), go: wp.array(dtype=wp.int32), controls: wp.array2d(dtype=control_dtype),
              mail: wp.array2d(dtype=wp.uint64), slot: int, mail_copy: wp.array2d(dtype=wp.uint64)):  # fmt: skip
        """A NaN action flags its world (bad[w]) and clears the go flag, which only the host sets
        again; the actions clipped to [−bound, bound] in place (NaN as 0); with ``scaled``, the
        controls a × scale [N, N·m] (max effort / bound: the bound maps to the drive's max
        effort).  ``mailed``: the actions read from the caller's float32 (N, A) batch at
        mail[slot, 0], clipped into ``a``, and mail[slot] copied to ``mail_copy[slot]`` (device
        memory, for ``finish_step``; else ``mail`` and ``mail_copy`` are unused)."""
        w = wp.tid()
        b = bool(False)
        src = a
        if wp.static(mailed):
            src = wp.array(ptr=mail[slot, 0], shape=(a.shape[0], a.shape[1]), dtype=wp.float32)
            if w == 0:
                mail_copy[slot, 0] = mail[slot, 0]
                mail_copy[slot, 1] = mail[slot, 1]
        for j in range(a.shape[1]):
            x = src[w, j]
            if wp.isnan(x):
                b = True
                x = 0.0
            x = wp.clamp(x, -bound, bound)
            a[w, j] = x
            if wp.static(scaled):
                controls[w, j] = control_dtype(x * scale[j])
        bad[w] = b
        if b:
            go[0] = 0

    return check


@functools.lru_cache(maxsize=None)
def finish_step(mailed: bool = False):
    """The kernel that ends world w's env step (below); ``mailed``: its outputs go to the step's
    fresh buffer at mail[slot, 1] and its done and bad rows to host_flags[slot] (else to ``out_obs``,
    ``out_reward`` and ``flags``; ``mail`` and ``host_flags`` unused)."""

    @wp.kernel(module="unique")  # a variant made later must not reload the others (in a graph)
    def finish(outcome: wp.array2d(dtype=wp.float32),
               status: wp.array(dtype=wp.int32), go: wp.array(dtype=wp.int32), pending: wp.array(dtype=wp.int32),
               elapsed: wp.array(dtype=wp.int64), max_steps: wp.int64, out_obs: wp.array2d(dtype=wp.float32),
               out_reward: wp.array(dtype=wp.float32), out_status: wp.array(dtype=wp.int32),
               flags: wp.array2d(dtype=wp.bool),
               mail: wp.array2d(dtype=wp.uint64), slot: int, host_flags: wp.array3d(dtype=wp.bool)):  # fmt: skip
        """World w's outcome from the task's, ``outcome[w]``: the observation (d columns), the reward
        and the termination (1 or 0), packed in one array so that torch.compile can write them in
        one kernel (arrays of two sizes are a kernel each): failed where its
        solve failed or an observation is not finite (zero observation and reward, terminated); a
        world reset in this step (pending, when the step ran) has reward 0 and neither flag;
        truncated at ``max_steps`` env steps (none when negative).  flags rows: terminated,
        truncated, failed, done (and bad, the check's); done becomes the next step's pending mask
        unless the step was refused; the world's status is copied to ``out_status``.  Mailed, the
        buffer holds the observations (N, d) and rewards (float32), the status (int32), then the
        rows terminated, truncated, failed (bytes): ``DeviceStep.unpack`` (device_step.py)."""
        w = wp.tid()
        n = outcome.shape[0]
        d = outcome.shape[1] - 2
        o = out_obs
        r_out = out_reward
        s_out = out_status
        f_out = flags
        if wp.static(mailed):
            p = mail[slot, 1]
            o = wp.array(ptr=p, shape=(n, d), dtype=wp.float32)
            r_out = wp.array(ptr=p + wp.uint64(4 * n * d), shape=(n,), dtype=wp.float32)
            s_out = wp.array(ptr=p + wp.uint64(4 * n * (d + 1)), shape=(n,), dtype=wp.int32)
            f_out = wp.array(ptr=p + wp.uint64(4 * n * (d + 2)), shape=(3, n), dtype=wp.bool)
        s_out[w] = status[w]
        failed = bool(status[w] != 0)
        for j in range(d):
            if not wp.isfinite(outcome[w, j]):
                failed = True
        ran = go[0] != 0
        reset = ran and pending[w] != 0
        terminated = (outcome[w, d + 1] != 0.0 or failed) and not reset
        truncated = max_steps >= wp.int64(0) and elapsed[w] >= max_steps and not reset
        for j in range(d):
            x = outcome[w, j]
            if failed:
                x = 0.0
            o[w, j] = x
        r = outcome[w, d]
        if failed or reset:
            r = 0.0
        r_out[w] = r
        done = terminated or truncated
        f_out[0, w] = terminated
        f_out[1, w] = truncated
        f_out[2, w] = failed
        if wp.static(mailed):
            host_flags[slot, 0, w] = done
            host_flags[slot, 1, w] = flags[4, w]
        else:
            flags[3, w] = done
        if ran:
            pending[w] = wp.where(done, 1, 0)

    return finish
