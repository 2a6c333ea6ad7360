"""The vector env's per-step bookkeeping on the device as two Warp kernels (the device path of
``vector_env`` with Torch); the episode clocks tick in the autoreset's first launch (autoreset.py).

Each replaces a run of one-line Torch operations whose launches, not their arithmetic, are what
an env step costs beside the physics: on an H100 with 1,024 CartPole worlds, about 35 small
kernels took ~100 µs of device time a step against ~260 µs of physics.  One thread per world.
"""
import functools

import warp as wp


@functools.lru_cache(maxsize=None)
def check_actions(control_dtype, scaled: bool):
    """The kernel that checks, clips and (with ``scaled``) scales world w's actions."""

    @wp.kernel
    def check(a: wp.array2d(dtype=wp.float32), effort: wp.array(dtype=wp.float32), bad: wp.array(dtype=wp.bool),
              go: wp.array(dtype=wp.int32), controls: wp.array2d(dtype=control_dtype)):  # fmt: skip
        """A NaN action flags its world (bad[w]) and clears the go flag, which only the host sets
        again; the actions clipped to [−1, 1] in place (NaN as 0); with ``scaled``, the controls
        a × max effort [N, N·m]."""
        w = wp.tid()
        b = bool(False)
        for j in range(a.shape[1]):
            x = a[w, j]
            if wp.isnan(x):
                b = True
                x = 0.0
            x = wp.clamp(x, -1.0, 1.0)
            a[w, j] = x
            if wp.static(scaled):
                controls[w, j] = control_dtype(x * effort[j])
        bad[w] = b
        if b:
            go[0] = 0

    return check


@wp.kernel
def finish_step(obs: wp.array2d(dtype=wp.float32), reward: wp.array(dtype=wp.float32), term: wp.array(dtype=wp.bool),
                status: wp.array(dtype=wp.int32), go: wp.array(dtype=wp.int32), pending: wp.array(dtype=wp.int32),
                elapsed: wp.array(dtype=wp.int64), max_steps: wp.int64, out_obs: wp.array2d(dtype=wp.float32),
                out_reward: wp.array(dtype=wp.float32), flags: wp.array2d(dtype=wp.bool)):  # fmt: skip
    """World w's outcome from the task's observation, reward and termination: failed where its
    solve failed or an observation is not finite (zero observation and reward, terminated); a world
    reset in this step (pending, when the step ran) has reward 0 and neither flag; truncated at
    ``max_steps`` env steps (none when negative).  flags rows: terminated, truncated, failed, done;
    done becomes the next step's pending mask unless the step was refused."""
    w = wp.tid()
    failed = bool(status[w] != 0)
    for j in range(obs.shape[1]):
        if not wp.isfinite(obs[w, j]):
            failed = True
    ran = go[0] != 0
    reset = ran and pending[w] != 0
    terminated = (term[w] or failed) and not reset
    truncated = max_steps >= wp.int64(0) and elapsed[w] >= max_steps and not reset
    for j in range(obs.shape[1]):
        x = obs[w, j]
        if failed:
            x = 0.0
        out_obs[w, j] = x
    r = reward[w]
    if failed or reset:
        r = 0.0
    out_reward[w] = r
    done = terminated or truncated
    flags[0, w] = terminated
    flags[1, w] = truncated
    flags[2, w] = failed
    flags[3, w] = done
    if ran:
        pending[w] = wp.where(done, 1, 0)
