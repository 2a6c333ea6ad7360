"""The device rollout's Warp kernels: one thread per world does the work of a step's or a
rollout's dozens of small Torch kernels (:mod:`.graphed_rollout`, :mod:`.device_rollout`), with
the same float32 operations in the same order (a compiler may fuse a multiply and an add)."""
from __future__ import annotations

import contextlib

import torch as th
import warp as wp

__all__ = ["gae_kernel", "record_kernel", "warp_on_torch_stream"]

FLOATS = wp.array(dtype=wp.float32)
FLOATS2 = wp.array2d(dtype=wp.float32)
FLOATS3 = wp.array3d(dtype=wp.float32)
FLAGS = wp.array(dtype=wp.bool)


@wp.kernel
def record_kernel(pos: wp.array(dtype=wp.int64), next_obs: FLOATS2, reward: FLOATS, env_reward: FLOATS,
                  terminated: FLAGS, truncated: FLAGS, actions: FLOATS2, values: FLOATS, log_probs: FLOATS,
                  obs: FLOATS2, episode_starts: FLOATS, ended: FLAGS, ep_return: FLOATS,
                  ep_length: wp.array(dtype=wp.int64), b_obs: FLOATS3, b_actions: FLOATS3, b_rewards: FLOATS2,
                  b_episode_starts: FLOATS2, b_values: FLOATS2, b_log_probs: FLOATS2, b_valid: FLOATS2,
                  b_dones: FLOATS2, b_cuts: FLOATS2, b_ep_return: FLOATS2, b_ep_length: FLOATS2):  # fmt: skip
    """World i's step at buffer position ``pos[0]`` (:mod:`.graphed_rollout`, 3): the flags, the episode's
    return and length so far (then 0 where the episode ended), the transition
    ``(obs, action, reward, episode_start, value, log_prob)``, and the carry ``obs <- next_obs``,
    ``episode_start <- ended``, ``ended <- done``.  ``reward``: what the buffer stores (normalised
    or the env's); ``env_reward``: the env's own, which the episode's return sums; float32 as the
    buffer, the length stored as float32 of its int64 count."""
    i = wp.tid()
    p = int(pos[0])
    done = terminated[i] or truncated[i]
    valid = not ended[i]  # a world that ended at the previous step was reset by this one
    ret = ep_return[i]
    length = ep_length[i]
    if valid:
        ret += env_reward[i]
        length += wp.int64(1)
    b_ep_return[p, i] = ret
    b_ep_length[p, i] = float(length)
    if done:
        ret = 0.0
        length = wp.int64(0)
    ep_return[i] = ret
    ep_length[i] = length
    b_valid[p, i] = wp.where(valid, 1.0, 0.0)
    b_dones[p, i] = wp.where(done, 1.0, 0.0)
    b_cuts[p, i] = wp.where(truncated[i] and not terminated[i], 1.0, 0.0)
    for k in range(obs.shape[1]):
        b_obs[p, i, k] = obs[i, k]
        obs[i, k] = next_obs[i, k]
    for k in range(actions.shape[1]):
        b_actions[p, i, k] = actions[i, k]
    b_rewards[p, i] = reward[i]
    b_episode_starts[p, i] = episode_starts[i]
    b_values[p, i] = values[i]
    b_log_probs[p, i] = log_probs[i]
    episode_starts[i] = wp.where(ended[i], 1.0, 0.0)  # a reset step's observation opens an episode
    ended[i] = done


@contextlib.contextmanager
def warp_on_torch_stream(device: th.device):
    """Warp's launches on Torch's current stream (on a GPU), registered with Warp as an external
    capture while Torch captures that stream."""
    if device.type != "cuda":
        yield
        return
    stream = th.cuda.current_stream(device)
    ws = wp.stream_from_torch(stream)
    with wp.ScopedStream(ws, sync_enter=False):
        capturing = th.cuda.is_current_stream_capturing()
        if capturing:
            wp.capture_begin(stream=ws, external=True)
        try:
            yield
        finally:
            if capturing:
                wp.capture_end(stream=ws)


@wp.kernel
def gae_kernel(rewards: FLOATS2, values: FLOATS2, dones: FLOATS2, cuts: FLOATS2, last_values: FLOATS, gamma: float,
               gamma_lambda: float, advantages: FLOATS2, returns: FLOATS2):  # fmt: skip
    """GAE(lambda) of world i over a NEXT_STEP rollout's positions (n_steps, n_envs), backwards:
    ``V' = V_{t+1}`` (``last_values`` after the last position); a position cut by its time limit
    first gets ``r_t += gamma V'`` (stored); ``delta = r_t + gamma V' (1 - done_t) - V_t``,
    ``A_t = delta + gamma_lambda (1 - done_t) A_{t+1}``, ``returns = A + V``.  ``gamma_lambda``:
    float32 of the float64 product ``gamma * gae_lambda``, as SB3's arithmetic has it."""
    i = wp.tid()
    n = rewards.shape[0]
    last = float(0.0)
    for j in range(n):
        t = n - 1 - j
        next_value = last_values[i]
        if t + 1 < n:
            next_value = values[t + 1, i]
        r = rewards[t, i] + gamma * next_value * cuts[t, i]
        rewards[t, i] = r
        non_terminal = 1.0 - dones[t, i]
        delta = r + gamma * next_value * non_terminal - values[t, i]
        last = delta + gamma_lambda * non_terminal * last
        advantages[t, i] = last
        returns[t, i] = last + values[t, i]
