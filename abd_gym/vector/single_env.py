"""A task as a single-world ``gymnasium.Env``: its vector env with one world."""
from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode

from ..sim import inputs
from .single_step import HostStep, world_info
from .spaces import real_actions


class ABDEnv(gym.Env):
    """A task as a single-world ``gymnasium.Env`` (CPU by default): its vector env with one world,
    autoreset disabled and no internal time limit (``gym.make`` adds ``TimeLimit``).

    Same conventions as the vector env: actions clipped to the action space, a NaN action raises
    ``ValueError`` without stepping, ``reset(seed=...)`` seeds the initial-state draws,
    ``reset(options={"randomize": ...})`` randomises the physical parameters; ``env.sim`` is the
    simulator and ``env.vector_env`` the one-world batched env.

    On the CPU a step is :class:`~abd_gym.vector.single_step.HostStep`: the vector env's world's
    step, bit for bit, without its batching, and its physics one launch (the plan's
    ``one_launch``, unless ``simulator_options`` gives a plan), replayed from a captured graph.
    """

    vector_class: type  # the task's ABDVectorEnv subclass, set by each task
    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if not isinstance(getattr(cls, "vector_class", None), type):
            raise TypeError(f"{cls.__name__} must set vector_class to its task's ABDVectorEnv subclass")
        cls.metadata = {"render_modes": ["rgb_array"], "render_fps": cls.vector_class.metadata["render_fps"]}

    def __init__(self, render_mode: str | None = None, device="cpu", simulator_options: dict | None = None, **kwargs):
        options = dict(simulator_options or {})
        if str(device).startswith("cpu"):
            # one world: the fused kernel opens and closes the step itself, one launch instead of
            # five (the same step bit for bit: tests/test_graph.py, test_single_env.py)
            options.setdefault("plan", {"one_launch": True})
        self.vector_env = self.vector_class(num_envs=1, device=device, backend="numpy",
                                            autoreset_mode=AutoresetMode.DISABLED, max_episode_steps=None,
                                            render_mode=render_mode, simulator_options=options, **kwargs)  # fmt: skip
        self.observation_space = self.vector_env.single_observation_space
        self.action_space = self.vector_env.single_action_space
        self.render_mode = render_mode
        self._host_step = HostStep(self.vector_env) if self.vector_env.device.is_cpu else None

    def __getstate__(self):
        """The env without its HostStep, which holds views of the simulator's memory; the vector
        env pickles itself (ABDVectorEnv.__getstate__) and a copy builds its own HostStep."""
        state = dict(self.__dict__)
        state.pop("_host_step")
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._host_step = HostStep(self.vector_env) if self.vector_env.device.is_cpu else None

    @property
    def sim(self):
        """The one-world env's ``Simulator``."""
        return self.vector_env.sim

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        # a refused reset (the world's draws, a task's own reset_task: nothing written, the
        # vector env's resets) leaves this env's generator, its seed and its state as they were
        saved = self._np_random, self._np_random_seed, self.vector_env._rng_state()
        try:
            super().reset(seed=inputs.seed(seed))
            self.vector_env.np_random = self.np_random  # one generator: seeding this env seeds its world
            if self._host_step is not None and not options:
                return self._host_step.reset()
            obs, info = self.vector_env.reset(options=options)
        except Exception:
            self._np_random, self._np_random_seed = saved[:2]
            self.vector_env._set_rng_state(saved[2])
            raise
        return obs[0], world_info(info)

    def step(self, action):
        if self._host_step is not None:
            if not self.vector_env._has_reset:
                raise RuntimeError("call reset() before step()")
            return self._host_step.step(action)
        a = np.asarray(real_actions(action), dtype=np.float32).reshape(1, -1)
        obs, reward, terminated, truncated, info = self.vector_env.step(a)
        return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), world_info(info)

    def render(self):
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; create the env with render_mode='rgb_array'")
            return None
        return self.vector_env.render()[0]

    def close(self):
        self.vector_env.close()
