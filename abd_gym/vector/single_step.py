"""One world's env step on the CPU, as lean as the task's hooks allow (``ABDEnv.step``).

The vector env's step serves any batch on any device: it converts and checks the action batch,
writes the controls through ``Simulator.set_controls``, and packs the outcome into Gymnasium's
batched info layout, which the single env then unpacks.  For one world on the CPU each of those
is a few NumPy calls on arrays of one row, and together they cost more than the physics.  Here
the same step reads and writes the simulator's arrays in place (the CPU's device memory is the
host's), steps by replaying the simulator's captured graphs, and calls the task's own hooks
(``observe``, ``reward``, ``terminated``, ``info``) once each, so that the world takes the steps
the vector env's world takes, bit for bit (tests/test_single_env.py):

* the action: float32, clipped to the action space, ``× action_scale`` into the drives' controls
  (the default ``controls`` hook; a task's own goes through ``Simulator.set_controls``); NaN
  raises ``ValueError`` before anything is written;
* the physics: ``Simulator.step(frame_skip)`` (replayed through ``Simulator.stepper`` once
  captured), then the episode clock;
* a reset without options: the vector env's ``_reset_worlds`` of the world, then its observation;
* the outcome: ``observation()`` (float32, clipped), the status and the NaN check of a failed
  world (zero observation and reward, terminated), the reward as a Python float and the flags as
  bools; ``info`` holds the task's values and ``sim_status`` / ``sim_substeps`` /
  ``sim_energy_gained`` / ``sim_failed``, as the vector env's world 0 has them.

Where the task has the one-world hooks (``Task.world_observation``, ``world_reward``,
``world_terminated``) and no ``info`` of its own, and the simulator's controls are float32, the
step of a float32 action of the action space's shape runs in Python floats:

* the action's entries are clipped by comparison with the bounds (a NaN fails both and raises)
  and each control is the product a × scale of two float32 values, which a double holds
  exactly, rounded to float32 as the control array stores it: NumPy's float32 product;
* the observation is the hook's list clipped by comparison with the float32 bounds, then
  rounded to float32 (for bounds that are float32 values, clipping before rounding gives what
  rounding before clipping gives); the reward and termination hooks read its float32 values.

Anything else (another dtype or shape of action, another task) takes the steps above.
"""
from __future__ import annotations

import math

import numpy as np

from .spaces import real_actions
from .task import Task

FLOAT32 = np.dtype(np.float32)  # (NumPy's one instance: an identity test; another float32 byte order is not it)


class HostStep:
    """The env step of ``env`` (an ABDVectorEnv of one world, NumPy backend, on the CPU, no
    autoreset and no time limit: ABDEnv's)."""

    def __init__(self, env):
        if env.num_envs != 1 or env.xp is not np or not env.device.is_cpu:
            raise ValueError("HostStep steps one world with the NumPy backend on the CPU")
        self.env, self.sim = env, env.sim
        state = env.sim.state
        self.action = np.zeros((1, env.action_dim), dtype=np.float32)  # the clipped action, reused
        self.flat = self.action.reshape(-1)  # a view of it
        bound = float(env.action_bound)
        # the clip's bounds as float32 rows (np.clip's bounds ±bound, cast as NumPy casts them):
        # an array operand costs a ufunc less than a Python scalar
        self.low = np.full_like(self.action, -bound)
        self.high = np.full_like(self.action, bound)
        # the default controls hook writes a × action_scale straight into the simulator's array
        self.scale = env.action_scale if env.default_controls else None
        if self.scale is not None:
            self.control = env.sim.host_view(state.control)  # (1, num_drives)
            same = self.control.dtype == np.float32  # else the float32 product is converted on the write
            self.product = self.control if same else np.zeros_like(self.action)
        self.status = env.sim.host_view(state.status)
        self.substeps = env.sim.host_view(state.substeps)
        self.gained = env.sim.host_view(state.gained)
        self.elapsed = memoryview(env.episodes.elapsed)  # the episode clock (an int on read)
        self.own_info = type(env).info is not Task.info  # the default info hook has no values
        self.frame_skip = env.frame_skip
        self.zero_obs = np.zeros(env.single_observation_space.shape, dtype=np.float32)
        self.world = np.arange(1)  # the reset's world index
        self.lean = self._lean_hooks(env)
        self.physics = None  # Simulator.stepper(frame_skip), once the simulator has captured the step
        if self.lean:
            nj = env.sim.model.num_joints
            # the world's joint coordinates and rates (memoryviews of the simulator's memory)
            self.coord = memoryview(env.sim.host_view(state.coord)[0, :nj])
            self.rate = memoryview(env.sim.host_view(state.coord_vel)[0, :nj])
            self.obs_low, self.obs_high = env._obs_low.tolist(), env._obs_high.tolist()  # float32 values
            self.action_shape = env.single_action_space.shape
            self.bound_low, self.bound_high = float(self.low[0, 0]), float(self.high[0, 0])
            self.control_row = self.control[0]
            self.scales = np.broadcast_to(self.scale, (env.action_dim,)).tolist()
            self.flags = [memoryview(a) for a in (self.status, self.substeps, self.gained)]  # Python ints on read
            n = len(env.world_observation(self.coord.tolist(), self.rate.tolist()))
            if n != len(self.obs_low):
                raise ValueError(f"{type(env).__name__}.world_observation gives {n} values, the observation space "
                                 f"has {len(self.obs_low)}")  # fmt: skip

    def _lean_hooks(self, env) -> bool:
        """Whether the step runs in Python floats (module docstring): the task's one-world hooks, no
        info of its own, the default controls into float32 controls, one per action entry."""
        task = type(env)
        hooks = [task.world_observation, task.world_reward, task.world_terminated]
        if any(h is not None for h in hooks) and any(h is None for h in hooks):
            raise TypeError(f"{task.__name__} must define all of world_observation, world_reward and "
                            "world_terminated, or none")  # fmt: skip
        return (hooks[0] is not None and not self.own_info and self.scale is not None
                and self.product is self.control and self.control.shape[1] == env.action_dim
                and len(env.single_observation_space.shape) == 1)  # fmt: skip

    def set_action(self, action):
        """The action as the clipped float32 row ``self.action`` (a NaN raises, nothing written)."""
        a = np.asarray(real_actions(action), dtype=np.float32)
        row = self.action
        if a.size != row.size:
            raise ValueError(f"action must have {row.size} entries, got shape {a.shape}")
        # np.clip's arithmetic without its Python wrapper; NaN stays NaN through both
        np.maximum(a.reshape(row.shape), self.low, out=row)
        np.minimum(row, self.high, out=row)
        if math.isnan(self.flat.dot(self.flat)):  # Σ a² is NaN where an entry is (clipped, none is inf)
            raise ValueError(f"action contains NaN: {a.tolist()}; nothing was stepped")
        return row

    def write_controls(self, a):
        """The drives' inputs from the clipped action row ``a``."""
        if self.scale is None:
            self.sim.set_controls(self.env.controls(a))
        elif self.product is self.control:
            np.multiply(a, self.scale, out=self.control)
        else:
            np.multiply(a, self.scale, out=self.product)
            self.control[...] = self.product

    def observation(self):
        """(the observation as a float32 array, its values as a list): the one-world hook's list
        clipped to the observation space, then rounded (module docstring)."""
        row = np.array(self.clip(self.env.world_observation(self.coord.tolist(), self.rate.tolist())), dtype=np.float32)
        return row, row.tolist()

    def clip(self, obs: list) -> list:
        """``obs`` clipped in place to the observation space by comparison (a NaN fails both: kept)."""
        low, high = self.obs_low, self.obs_high
        i = 0
        for x in obs:
            if x < low[i]:
                obs[i] = low[i]
            elif x > high[i]:
                obs[i] = high[i]
            i += 1
        return obs

    def reset(self):
        """``(obs, info)`` of a reset without options: the vector env's reset of its world
        (``_reset_worlds``: parameters, initial state, clock, task values), without the parsing of
        options and masks that this reset does not have."""
        env = self.env
        env._reset_worlds(self.world, {})
        env._has_reset = True
        if self.lean:
            return self.observation()[0], {}
        return env.observation()[0], {}

    def step(self, action):
        """``(obs, reward, terminated, truncated, info)`` of one env step (module docstring): in Python
        floats for a float32 action of the action space's shape where the task has the one-world
        hooks, else ``numpy_step``."""
        if not (self.lean and type(action) is np.ndarray and action.dtype is FLOAT32
                and action.shape == self.action_shape):  # fmt: skip
            return self.numpy_step(action)
        low, high = self.bound_low, self.bound_high
        a = action.tolist()
        for i, x in enumerate(a):  # clipped by comparison; a NaN fails both and raises, nothing written
            if x < low:
                a[i] = low
            elif x > high:
                a[i] = high
            elif x != x:
                raise ValueError(f"action contains NaN: {action.tolist()}; nothing was stepped")
        controls, scales = self.control_row, self.scales
        for i, x in enumerate(a):
            controls[i] = x * scales[i]  # exact in a double, rounded to float32 by the store
        self.advance()
        env = self.env
        row, obs = self.observation()
        status, substeps, gained = self.flags
        s = sum(obs)  # NaN just where an entry is (clipped: none is inf, and the sum is finite)
        failed = status[0] != 0 or s != s
        info = {"sim_status": status[0], "sim_substeps": substeps[0], "sim_energy_gained": gained[0] != 0,
                "sim_failed": failed}  # fmt: skip
        if failed:
            return self.zero_obs.copy(), 0.0, True, False, info
        return row, env.world_reward(obs, a), bool(env.world_terminated(obs)), False, info

    def numpy_step(self, action):
        """``step`` of any action, through the task's batched hooks (module docstring)."""
        env = self.env
        a = self.set_action(action)
        self.write_controls(a)
        self.advance()
        obs = env.observation()
        status = int(self.status[0])
        row = obs[0]  # clipped: a non-finite entry is NaN, and Σ o² is NaN just where one is
        failed = status != 0 or math.isnan(row.dot(row))
        reward = float(np.float32(env.reward(obs, a)[0]))  # float32, as the vector env's reward
        terminated = bool(env.terminated(obs)[0]) or failed
        info = world_info(env.info(obs)) if self.own_info else {}
        info["sim_status"] = status
        info["sim_substeps"] = int(self.substeps[0])
        info["sim_energy_gained"] = bool(self.gained[0])
        info["sim_failed"] = failed
        if failed:
            return self.zero_obs.copy(), 0.0, True, False, info
        return row, reward, terminated, False, info

    def advance(self):
        """The physics of an env step, ``Simulator.step(frame_skip)``, replayed through
        ``Simulator.stepper`` once the simulator has captured it, then the episode clock."""
        if self.physics is None:
            self.sim.step(self.frame_skip)
            self.physics = self.sim.stepper(self.frame_skip)
        else:
            self.physics()
        self.elapsed[0] += 1


def world_info(info: dict) -> dict:
    """World 0's entries of a batched info dict: Python scalars or array rows, nested dicts alike;
    Gymnasium's ``"_key"`` masks left out."""
    out = {}
    for key, value in info.items():
        if key.startswith("_"):
            continue
        if isinstance(value, dict):
            out[key] = world_info(value)
        else:
            v = np.asarray(value)[0]
            out[key] = v.item() if v.ndim == 0 else v
    return out
