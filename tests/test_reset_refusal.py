"""A refused reset writes nothing: every door that resets worlds (reset with options, the
autoreset queues' top-up, set_state) draws and checks all it will write (the parameters against
which the state is checked, the state, the task values) before it writes any, so that after the
refusal every array (the model's parameters, the state, the task state, the episode counters,
the queues) and the generators are bit for bit as before."""
import copy

import numpy as np
import pytest
import warp as wp

from abd_gym.envs.reacher import ReacherVectorEnv
from abd_gym.vector.single_env import ABDEnv

N = 4


class Poisoned(ReacherVectorEnv):
    """The Reacher with the last world's elbow drawn at ``elbow`` (None: as drawn), and the last
    row of each draw for the autoreset queues (from a generator other than np_random) at
    ``queue_elbow``."""

    elbow = None
    queue_elbow = None

    def initial_state(self, n, rng, options):
        x, v = super().initial_state(n, rng, options)
        elbow = self.elbow if rng is self.np_random else self.queue_elbow
        if elbow is not None:
            x[-1, 1] = elbow
        return x, v


def _everything(env):
    """Every value a reset can write: the env's state (the simulator's, the parameters in force,
    the episodes, the queues, the pending mask; the generators as their bit states) and every
    array of the simulator's model."""
    snap = env.get_state()
    gens = snap.pop("rng")
    out = {"state": snap, "rng": [None if g is None else copy.deepcopy(g.bit_generator.state)
                                  for g in (gens[0], gens[2])] + [gens[1]],
           "spawned": [None if g is None else g.bit_generator.seed_seq.n_children_spawned for g in (gens[0], gens[2])],
           "spec": copy.deepcopy(env.parameters.spec)}  # fmt: skip
    out["model"] = {k: v.numpy().copy() for k, v in vars(env.sim.model).items() if isinstance(v, wp.array)}
    return out


def _same(a, b, where="env"):
    if isinstance(a, dict):
        assert set(a) == set(b), where
        for k in a:
            _same(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (u, v) in enumerate(zip(a, b)):
            _same(u, v, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        np.testing.assert_array_equal(a, b, err_msg=where)
        assert a.dtype == b.dtype, where
    else:
        assert a == b, where


@pytest.fixture
def env():
    env = Poisoned(num_envs=N, max_episode_steps=3)
    env.reset(seed=0)
    env.step(np.zeros((N, 2), np.float32))
    return env


def test_a_reset_refused_against_the_limits_it_draws_writes_nothing(env):
    """An elbow at 2 rad is inside its ±2.8 rad limit but not inside the ±0.28 rad the reset's
    randomisation draws for it: refused before the masses, strengths and limits are written."""
    before = _everything(env)
    env.elbow = 2.0
    spec = {"limit_scale": (0.1, 0.1), "mass_scale": (0.5, 2.0), "strength_ratio": (1.0, 2.0)}
    with pytest.raises(ValueError, match="elbow"):
        env.reset(seed=5, options={"randomize": spec, "reset_mask": np.array([False, True, False, True])})
    _same(_everything(env), before)
    env.elbow = None  # the same reset then goes through
    env.reset(seed=5, options={"randomize": spec, "reset_mask": np.array([False, True, False, True])})
    assert env.parameters.limits[1][1, 1] == pytest.approx(0.28)


@pytest.mark.parametrize("bad", ["nan_coordinate", "fast_rate", "nan_target", "unknown_option"])
def test_a_refused_reset_writes_nothing(env, bad):
    """A NaN coordinate, a rate past the step's turn, a NaN target (task values), an unknown
    option: the env as before, spec and generators included."""
    env.reset(seed=1, options={"randomize": {"mass_scale": (0.5, 2.0)}})
    env.step(np.zeros((N, 2), np.float32))
    before = _everything(env)
    options = {"randomize": {"mass_scale": (3.0, 4.0)}}
    if bad == "nan_coordinate":
        env.elbow = np.nan
    elif bad == "fast_rate":
        env.initial_state = lambda n, rng, options: (np.zeros((n, 2)), np.full((n, 2), 5e3))
    elif bad == "nan_target":
        options["target"] = [np.nan, 0.0]
    else:
        options["no_such_option"] = 1
    with pytest.raises(ValueError):
        env.reset(seed=7, options=options)
    _same(_everything(env), before)


def test_a_refused_queue_top_up_leaves_the_step_unrun(env):
    """The autoreset queues' top-up (episodes of 3 steps: every world takes a row each 3 steps)
    draws a row the checks refuse: the step that draws it raises before its physics, with every
    array (the worlds' states, clocks, queues, their counts), the generators and the spawn counts
    bit for bit as before the call, again on a second call; the env then steps as a twin never
    refused."""
    ne = env.next_episodes
    assert ne is not None
    env.queue_elbow = 1e9  # beyond the state bound
    a = np.full((N, 2), 0.5, np.float32)
    for steps in range(3 * ne.depth):
        before, saved = _everything(env), env.get_state()
        try:
            env.step(a)
        except ValueError as err:
            assert "initial" in str(err)
            break
    else:
        pytest.fail("no top-up was refused")
    assert steps > ne.depth // 2  # a top-up in mid-run, after autoresets used the queues
    _same(_everything(env), before)
    with pytest.raises(ValueError, match="initial"):
        env.step(a)
    _same(_everything(env), before)
    env.queue_elbow = None
    twin = Poisoned(num_envs=N, max_episode_steps=3)
    twin.set_state(saved)
    for _ in range(4):
        for e in (env, twin):
            e.step(a)
    _same(_everything(env), _everything(twin))


@pytest.mark.parametrize("seed", [9, None])
def test_a_full_reset_whose_queues_are_refused_writes_nothing(env, seed):
    """A full reset draws every world's next episodes for the autoreset queues too: a row of
    them refused (an elbow beyond the state bound) refuses the reset before any world, queue or
    generator is written, the spawn of the queues' generator included (seed None: the same
    generator, whose next spawn must stay the one it was)."""
    before, saved = _everything(env), env.get_state()
    env.queue_elbow = 1e9
    with pytest.raises(ValueError, match="initial"):
        env.reset(seed=seed)
    _same(_everything(env), before)
    env.queue_elbow = None  # the same reset then goes through as in an env never refused
    twin = Poisoned(num_envs=N, max_episode_steps=3)
    twin.set_state(saved)
    for e in (env, twin):
        e.reset(seed=seed)
        e.step(np.zeros((N, 2), np.float32))
    _same(_everything(env), _everything(twin))


def test_a_full_reset_checks_its_queues_against_the_limits_it_draws(env):
    """The queues' rows are checked against the limits the same reset draws (±0.28 rad here),
    before those limits are written."""
    before = _everything(env)
    env.queue_elbow = 2.0  # inside the ±2.8 rad limit in force
    with pytest.raises(ValueError, match="elbow"):
        env.reset(seed=5, options={"randomize": {"limit_scale": (0.1, 0.1)}})
    _same(_everything(env), before)


def test_a_reset_refused_for_a_parameter_the_simulator_refuses_writes_nothing(env):
    """Drawn masses past the simulator's bound are refused by the parameters' own checks, before
    any parameter is written."""
    before = _everything(env)
    with pytest.raises(ValueError, match="mass"):
        env.reset(seed=5, options={"randomize": {"strength_ratio": (1.0, 2.0), "mass_scale": (1e30, 1e30)}})
    _same(_everything(env), before)


class OwnTarget(ReacherVectorEnv):
    """The Reacher with a ``reset_task`` of its own: it draws the targets, writes them, then
    refuses the draw where a target lies farther than ``reach`` (None: none refused) from the
    base, as a task's own code may do after the reset has written the worlds."""

    reach = None

    def reset_task(self, idx, rng, options):
        target = rng.uniform(-0.2, 0.2, size=(len(idx), 2))
        self.put(self.target, idx, target)
        if self.reach is not None and np.any(np.hypot(target[:, 0], target[:, 1]) > self.reach):
            raise RuntimeError("target out of reach")


@pytest.mark.parametrize("mask", [None, [True, False, True, True]])
def test_a_reset_refused_by_the_task_s_own_reset_task_writes_nothing(mask):
    """A task's own ``reset_task`` runs after the reset has written the parameters, the states and
    the clocks, writes its targets and then raises: every array, the spec and the generator are
    put back bit for bit, and the env then resets and steps as a twin never refused."""
    env = OwnTarget(num_envs=N, max_episode_steps=3)
    assert env.next_episodes is None  # (its resets run on the host)
    env.reset(seed=0, options={"randomize": {"mass_scale": (0.5, 2.0)}})
    env.step(np.zeros((N, 2), np.float32))
    before, saved = _everything(env), env.get_state()
    env.reach = 0.05  # a target in [-0.2, 0.2]^2 beyond 0.05 m in one of 3 or 4 worlds: all but certain
    options = {"randomize": {"mass_scale": (3.0, 4.0), "limit_scale": (0.5, 0.5), "strength_ratio": (1.0, 2.0)}}
    if mask is not None:
        options["reset_mask"] = np.array(mask)
    with pytest.raises(RuntimeError, match="out of reach"):
        env.reset(seed=7, options=options)
    _same(_everything(env), before)
    env.reach = None
    twin = OwnTarget(num_envs=N, max_episode_steps=3)
    twin.set_state(saved)
    for e in (env, twin):
        e.reset(seed=7, options=dict(options))
        for _ in range(4):  # through an autoreset (episodes of 3 steps), on the host
            e.step(np.full((N, 2), 0.5, np.float32))
    _same(_everything(env), _everything(twin))


class OneOwnTarget(ABDEnv):
    vector_class = OwnTarget


def _world(env):
    """_everything of a one-world env's vector env, with its own generator's bit state and seed."""
    gen = env._np_random
    return dict(_everything(env.vector_env), own=[None if gen is None else copy.deepcopy(gen.bit_generator.state),
                                                  env._np_random_seed])  # fmt: skip


@pytest.mark.parametrize("seed", [7, None])
def test_a_one_world_reset_refused_by_the_task_s_own_reset_task_writes_nothing(seed):
    """The one-world env's reset (its plain-Python path) of a task whose own ``reset_task``
    raises: the world, the generators (seeded anew or not) and the seed as before, and the env
    then resets and steps as a twin never refused."""
    env, twin = OneOwnTarget(), OneOwnTarget()
    for e in (env, twin):
        e.reset(seed=0)
        e.step(np.zeros(2, np.float32))
    before = _world(env)
    env.vector_env.reach = 1e-3  # a target in [-0.2, 0.2]^2 within 1 mm: all but impossible
    with pytest.raises(RuntimeError, match="out of reach"):
        env.reset(seed=seed)
    _same(_world(env), before)
    env.vector_env.reach = None
    for e in (env, twin):
        e.reset(seed=seed)
        e.step(np.full(2, 0.5, np.float32))
    _same(_world(env), _world(twin))


@pytest.mark.parametrize("bad", ["coordinate", "mass", "episodes", "limits"])
def test_a_refused_set_state_writes_nothing(env, bad):
    """set_state of a snapshot with a joint past its limit, a negative mass, a clock of another
    shape, or limits the state lies beyond: the env as before."""
    saved = env.get_state()
    env.reset(seed=3, options={"randomize": {"mass_scale": (0.5, 2.0)}})
    env.step(np.zeros((N, 2), np.float32))
    before = _everything(env)
    if bad == "coordinate":
        saved["sim"]["coord"][2, 1] = 10.0
    elif bad == "mass":
        saved["parameters"]["body_mass"][1, 1] = -1.0
    elif bad == "episodes":
        saved["episodes"]["elapsed"] = saved["episodes"]["elapsed"][:2]
    else:  # the saved state inside the limits in force, outside the snapshot's own
        saved["parameters"]["limits"][1][:, :2] = [-0.01, 0.01]
        saved["sim"]["coord"][:, 1] = 2.0  # (a limit holds 1 rad past its bound here)
    with pytest.raises(ValueError):
        env.set_state(saved)
    _same(_everything(env), before)
