"""Every public setter and constructor fuzzed with NaN, ±inf, 1e30, complex, string, object and
bool values, wrong shapes, non-rotations and bad world indices: each is refused with a ValueError
or TypeError that abd_gym raises itself (not NumPy or Warp from inside), naming the argument, and
no world changes."""
import os
import traceback

import numpy as np
import pytest
import warp as wp

import abd_gym as ag
from abd_gym.sim import mechanisms, shapes
from abd_gym.sim.scene import Scene

W = 3
PACKAGE = os.path.dirname(ag.__file__)
BAD_NUMBERS = [np.nan, np.inf, -np.inf, 1e30, 1 + 1j, "1.0", None, True]
BAD_WORLDS = [1.7, [1.0], -1, W, [0, 0], "0", [[None]], np.nan]
NON_ROTATIONS = {"zero": np.zeros((3, 3)), "scaled": 1000.0 * np.eye(3), "reflection": np.diag([1.0, 1.0, -1.0]),
                 "shear": np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])}  # fmt: skip


def _scene():
    """A cart-pole with both joints limited and the slider driven: every kind of per-world input."""
    scene = mechanisms.cartpole()
    scene.add_revolute_limit(1, -1.0, 1.0, 1e3)
    return scene


@pytest.fixture(scope="module")
def sim():
    s = ag.Simulator(_scene(), num_worlds=W, dt=0.01)
    s.set_joint_state([[0.1, 0.2], [0.0, -0.3], [-0.5, 0.4]], [[0.5, 1.0], [0.0, 0.0], [-0.2, 0.3]])
    s.step(2)
    return s


def _bad(value, shape):
    """``value`` as the argument: a scalar as is, else an array of ``shape`` holding it."""
    if value is None or isinstance(value, (str, bool)):
        return np.full(shape, value, dtype=object) if value is None else np.full(shape, value)
    return np.full(shape, value)


def _refused(call, name):
    """``call()`` raises a ValueError or TypeError, raised in abd_gym's own code, naming ``name``."""
    with pytest.raises((ValueError, TypeError)) as info:
        call()
    frames = traceback.extract_tb(info.value.__traceback__)
    assert frames[-1].filename.startswith(PACKAGE), f"raised inside {frames[-1].filename}: {info.value}"
    assert name in str(info.value), f"{name!r} not named in: {info.value}"


def _same(a: dict, b: dict):
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def _setters(sim):
    """{(setter, argument): (call(value), shape of a good value)} of every per-world argument."""
    q = sim.body_q()
    p, R = q[..., :3], q[..., 3:].reshape(W, -1, 3, 3)
    x = sim.joint_coordinates()
    return {
        ("set_controls", "controls"): (lambda v: sim.set_controls(v), (W, 1)),
        ("set_body_states", "positions"): (lambda v: sim.set_body_states(v, R), p.shape),
        ("set_body_states", "rotations"): (lambda v: sim.set_body_states(p, v), R.shape),
        ("set_body_states", "linear_velocities"): (lambda v: sim.set_body_states(p, R, v), p.shape),
        ("set_body_states", "angular_velocities"): (lambda v: sim.set_body_states(p, R, None, v), p.shape),
        ("set_joint_state", "coordinates"): (lambda v: sim.set_joint_state(v), x.shape),
        ("set_joint_state", "velocities"): (lambda v: sim.set_joint_state(x, v), x.shape),
        ("set_limit", "lower"): (lambda v: sim.set_limit(0, lower=v), (W,)),
        ("set_limit", "upper"): (lambda v: sim.set_limit(0, upper=v), (W,)),
        ("set_limit", "strength"): (lambda v: sim.set_limit(0, strength=v), (W,)),
        ("set_body_mass", "mass"): (lambda v: sim.set_body_mass(v), (W, 3)),
        ("set_joint_strength", "strength_ratio"): (lambda v: sim.set_joint_strength(v), (W, 2)),
    }


def test_every_public_setter_is_fuzzed(sim):
    covered = {setter for setter, _ in _setters(sim)} | {"set_state", "set_joint_state_where"}
    public = {n for n in dir(ag.Simulator) if n.startswith("set_")}
    assert public <= covered, f"setters without a fuzz case: {sorted(public - covered)}"


@pytest.mark.parametrize("value", BAD_NUMBERS + ["shape"], ids=repr)
def test_bad_values_are_refused_at_every_setter(sim, value):
    before = sim.get_state()
    for (setter, arg), (call, shape) in _setters(sim).items():
        bad = np.zeros((7, 5)) if value == "shape" else _bad(value, shape)
        _refused(lambda: call(bad), arg)
        _same(sim.get_state(), before)


@pytest.mark.parametrize("worlds", BAD_WORLDS, ids=repr)
def test_bad_world_indices_are_refused_at_every_setter(sim, worlds):
    before = sim.get_state()
    calls = [lambda: sim.set_controls(0.0, worlds=worlds), lambda: sim.set_joint_state(0.0, worlds=worlds),
             lambda: sim.set_body_mass(1.0, worlds=worlds), lambda: sim.set_joint_strength(100.0, worlds=worlds),
             lambda: sim.set_limit(0, strength=1e3, worlds=worlds), lambda: sim.reset(worlds),
             lambda: sim.get_state(worlds), lambda: sim.set_state(before, worlds)]  # fmt: skip
    for call in calls:
        _refused(call, "world")
        _same(sim.get_state(), before)


@pytest.mark.parametrize("kind", sorted(NON_ROTATIONS))
def test_non_rotations_are_refused(sim, kind):
    before = sim.get_state()
    q = sim.body_q()
    R = q[..., 3:].reshape(W, -1, 3, 3).copy()
    R[1, 2] = NON_ROTATIONS[kind]
    _refused(lambda: sim.set_body_states(q[..., :3], R), "rotations: body 'pole' in world 1 is not a rotation")
    state = sim.get_state()
    state["q"][1, 2, 3:] = NON_ROTATIONS[kind].reshape(-1)
    _refused(lambda: sim.set_state(state), "state['q']: body 'pole' in world 1 is not a rotation")
    _same(sim.get_state(), before)
    _refused(lambda: Scene().add_body(shapes.Box((0.1, 0.1, 0.1)), rotation=NON_ROTATIONS[kind]), "rotation")


def test_limits_beyond_what_they_hold_are_refused(sim):
    """The slider's limit is ±2.4 m (width 4.8 m, its scale); the pole's ±1 rad (scale 1 rad)."""
    before = sim.get_state()
    q = sim.body_q()
    p, R = q[..., :3].copy(), q[..., 3:].reshape(W, -1, 3, 3)
    p[2, 1:, 0] += 10.0  # the cart and the pole 10 m along the track: 7.6 m past the bound
    _refused(lambda: sim.set_body_states(p, R), "positions: joint 'prismatic0' in world 2")
    _same(sim.get_state(), before)
    _refused(lambda: sim.set_joint_state([[0.0, 2.5]] * W), "coordinates: joint 'revolute1' in world 0")
    _refused(lambda: sim.set_limit(0, lower=5.0, upper=6.0, worlds=[1]), "set_limit: joint 'prismatic0' in world 1")
    _refused(lambda: sim.set_limit(1, lower=0.5, upper=0.4), "lower (0.5) must not exceed upper")
    _refused(lambda: sim.set_limit(0, lower=0.6, upper=0.5), "lower (0.6) must not exceed upper")
    state = sim.get_state()
    state["coord"][0, 1] = 3.0
    _refused(lambda: sim.set_state(state), "state['coord']: joint 'revolute1' in world 0")
    _same(sim.get_state(), before)
    scene = mechanisms.slider()
    _refused(lambda: scene.add_prismatic_limit(0, 5.0, 6.0), "zero pose")


def test_bad_state_entries_are_refused(sim):
    before = sim.get_state()
    for change, name in [(lambda s: s.pop("qd"), "missing ['qd']"), (lambda s: s.update(extra=1), "unknown ['extra']"),
                         (lambda s: s.update(q=s["q"].astype(np.float64)), "state['q'] must be float32"),
                         (lambda s: s.update(status=np.full(W, 7, np.int32)), "state['status'] has an unknown code 7"),
                         (lambda s: s["qd"].__setitem__((0, 1, 0), np.nan), "state['qd'] has a non-finite value")]:  # fmt: skip
        state = sim.get_state()
        change(state)
        _refused(lambda: sim.set_state(state), name)
        _same(sim.get_state(), before)
    _refused(lambda: sim.set_state([1, 2]), "state must be a dict")


def test_device_arrays_of_the_wrong_kind_are_refused(sim):
    xx = wp.zeros((W, 2, 2), dtype=wp.float32)
    _refused(lambda: sim.set_joint_state_where(wp.zeros(W, dtype=wp.float32), xx), "mask")
    _refused(lambda: sim.set_joint_state_where(wp.zeros(W, dtype=wp.int32), wp.zeros((W, 2), dtype=wp.float32)), "xx")


@pytest.mark.parametrize("arg,values", [
    ("num_worlds", [0, -1, 2.5, 2.0, "2", True, None]),
    ("dt", [0.0, -0.01, np.nan, np.inf, 1 + 1j, "0.01", True]),
    ("tol", [0.0, -1.0, np.nan, np.inf, "1e-5"]),
    ("max_iterations", [0, -1, 2.5, np.float64(3.0), "5"]),
    ("max_line_search", [0, -1, 1.5]),
    ("quadratic_stop", [-1.0, np.nan, np.inf, "1"]),
    ("reuse_factor", ["yes", 1]),
    ("integrator", ["rk4", 3]),
    ("dtype", ["float16", "complex64", 7, "nonsense"]),
    ("device", ["cuda:99", "tpu", 3.5]),
])  # fmt: skip
def test_bad_constructor_arguments_are_refused(arg, values):
    scene = mechanisms.pendulum()
    for v in values:
        _refused(lambda: ag.Simulator(scene, **{"num_worlds": 1, arg: v}), arg)


def test_real_numpy_scalars_are_accepted(sim):
    """np.float32, np.int64 and 0-d arrays are numbers like any other."""
    s = ag.Simulator(_scene(), num_worlds=np.int64(2), dt=np.float32(0.01), tol=np.float64(1e-5),
                     max_iterations=np.int32(20))  # fmt: skip
    assert s.dt == pytest.approx(0.01) and s.num_worlds == 2
    s.step(np.int64(1))
    s.set_joint_state(np.float32([[0.1, 0.0], [0.2, 0.0]]), worlds=np.array([0, 1], dtype=np.uint8))


@pytest.mark.parametrize("value", [np.nan, np.inf, 1 + 1j, "x", [1, 2]], ids=repr)
def test_bad_steps_are_refused(sim, value):
    before = sim.get_state()
    for call in (sim.step, sim.tick, sim.launch_step):
        _refused(lambda: call(value), "num_steps")
    _refused(lambda: sim.step(-1), "num_steps")
    _refused(lambda: sim.step(2.5), "num_steps")
    _same(sim.get_state(), before)


@pytest.mark.parametrize("value", [np.nan, np.inf, 1 + 1j, "x", None, [1.0, 2.0]], ids=repr)
def test_bad_scene_arguments_are_refused(value):
    box = shapes.Box((0.1, 0.1, 0.1))

    def scene():
        s = Scene()
        s.add_body(box, fixed=True, name="base")
        s.add_body(box, mass=1.0, name="b")
        s.add_revolute_joint("base", "b", (0, 0, 0), (0, 1, 0))
        s.add_prismatic_joint("base", "b", (0, 0, 0), (1, 0, 0))
        return s

    vec = value if isinstance(value, list) else [value, 0.0, 0.0]
    calls = {
        "gravity": lambda: Scene(gravity=vec),
        "mass": lambda: Scene().add_body(box, mass=value),
        "density": lambda: Scene().add_body(box, density=value),
        "stiffness": lambda: Scene().add_body(box, stiffness=value),
        "position": lambda: Scene().add_body(box, position=vec),
        "linear_velocity": lambda: Scene().add_body(box, linear_velocity=vec),
        "angular_velocity": lambda: Scene().add_body(box, angular_velocity=vec),
        "anchor": lambda: scene().add_revolute_joint("base", "b", vec, (0, 1, 0)),
        "axis": lambda: scene().add_revolute_joint("base", "b", (0, 0, 0), vec),
        "strength_ratio": lambda: scene().add_fixed_joint("base", "b", strength_ratio=value),
        "half_length": lambda: scene().add_revolute_joint("base", "b", (0, 0, 0), (0, 1, 0), half_length=value),
        "lower": lambda: scene().add_revolute_limit(0, value, 1.0),
        "upper": lambda: scene().add_prismatic_limit(1, -1.0, value),
        "strength": lambda: scene().add_prismatic_limit(1, -1.0, 1.0, strength=value),
        "damping": lambda: scene().set_joint_passive(0, damping=value),
        "armature": lambda: scene().set_joint_passive(0, armature=value),
        "max_effort": lambda: scene().add_drive(0, max_effort=value if value is not np.inf else -np.inf),
        "half_extents": lambda: shapes.Box(vec if isinstance(value, list) else (value, 0.1, 0.1)),
        "radius": lambda: shapes.Sphere(value),
    }
    for name, call in calls.items():
        if name in ("lower", "upper") and value is np.inf:
            continue  # refused as beyond [-pi, pi] / as the range, named otherwise
        if value is None and name in ("mass", "stiffness", "strength_ratio", "half_length"):
            continue  # None: derived
        _refused(call, name)


def test_per_world_parameters_rerun_the_conditioning_warnings():
    """A mass ratio of 1e6 set after the build (float32): the build's warning, for the world touched."""
    sim = ag.Simulator(mechanisms.double_pendulum(), num_worlds=W, dt=0.01)
    with pytest.warns(RuntimeWarning, match=r"joint 'revolute1' in worlds \[1\]: K/m up to 1e\+08"), \
            pytest.warns(RuntimeWarning, match=r"body 'link1' in worlds \[1\]: mass 1e-06 kg"):
        sim.set_body_mass([[1.0, 1e-6]], bodies=["link0", "link1"], worlds=[1])
    with pytest.warns(RuntimeWarning, match=r"joint 'revolute0' in worlds \[0, 2\]"):
        sim.set_joint_strength([[1e7, 100.0], [1e7, 100.0]], worlds=[0, 2])


def test_torch_controls_of_a_non_real_dtype_are_refused(sim):
    torch = pytest.importorskip("torch")
    for dtype in (torch.complex64, torch.bool):
        _refused(lambda: sim.set_controls(torch.zeros((W, 1), dtype=dtype)), "controls")
    sim.set_controls(torch.zeros((W, 1), dtype=torch.float64))


def test_names_and_flags_of_the_wrong_type_are_refused():
    box = shapes.Box((0.1, 0.1, 0.1))
    _refused(lambda: Scene().add_body(box, fixed="no"), "fixed")
    _refused(lambda: Scene().add_body(box, name=3), "name")
    s = Scene()
    s.add_body(box, fixed=True)
    s.add_body(box)
    _refused(lambda: s.add_revolute_joint(0, 1, (0, 0, 0), (0, 1, 0), name=["a"]), "name")


BAD_ITEMS = [1.5, -1, 99, np.nan, "nope", None, True, 1 + 1j, np.float64(1.0)]


@pytest.mark.parametrize("item", BAD_ITEMS, ids=repr)
def test_bad_joint_and_body_indices_are_refused(sim, item):
    """Non-integer, out-of-range, unknown-name and non-real joint and body indices, and a flag
    that is not a bool."""
    before = sim.get_state()
    _refused(lambda: sim.set_limit(item, strength=1e3), "joint")
    _refused(lambda: sim.set_joint_strength(100.0, joints=[item]), "joint")
    _refused(lambda: sim.set_body_mass(1.0, bodies=[item]), "body")
    if not isinstance(item, bool):
        _refused(lambda: sim.set_limit(1, strength=1e3, check_state=item), "check_state")
    _same(sim.get_state(), before)


@pytest.fixture(scope="module")
def env():
    from abd_gym.envs.cartpole import CartPoleVectorEnv

    env = CartPoleVectorEnv(num_envs=2)
    env.reset(seed=0)
    yield env
    env.close()


BAD_ACTIONS = [np.nan, np.full((2, 1), 1 + 1j), np.full((2, 1), "x"), np.full((2, 1), None, dtype=object),
               np.zeros((2, 1), dtype=bool), np.zeros((3, 1)), np.zeros((2, 2)), [[0.0], [0.0, 1.0]]]  # fmt: skip


@pytest.mark.parametrize("actions", BAD_ACTIONS, ids=lambda a: repr(np.asarray(a, dtype=object).ravel()[:2]))
def test_the_vector_env_refuses_bad_actions(env, actions):
    before = env.sim.get_state()
    bad = np.full((2, 1), actions) if isinstance(actions, float) else actions
    _refused(lambda: env.step(bad), "actions")
    _same(env.sim.get_state(), before)


def test_the_vector_env_refuses_bad_arguments(env):
    """Its constructor's counts, reset's seed and options, set_state's entries."""
    from abd_gym.envs.cartpole import CartPoleVectorEnv

    for n in (0, -1, 2.5, "2", None, True):
        _refused(lambda: CartPoleVectorEnv(num_envs=n), "num_envs")
    for steps in (0, 2.5, "10"):
        _refused(lambda: CartPoleVectorEnv(num_envs=1, max_episode_steps=steps), "max_episode_steps")
    before = env.sim.get_state()
    for seed in (1.5, -1, "x", np.nan, True):
        _refused(lambda: env.reset(seed=seed), "seed")
    for options, name in (({"reset_mask": np.array([1, 0])}, "reset_mask"), ({"reset_mask": np.ones(3, bool)}, "reset_mask"),
                          ({"bogus": 1}, "reset options")):  # fmt: skip
        _refused(lambda: env.reset(options=options), name)
    for state in (None, 3, {}, {"sim": 1}):
        _refused(lambda: env.set_state(state), "state")
    state = env.get_state()
    state["sim"]["qd"] = state["sim"]["qd"] * np.nan
    _refused(lambda: env.set_state(state), "state['qd']")
    _same(env.sim.get_state(), before)


def test_the_single_env_refuses_non_real_actions():
    from abd_gym.envs.pendulum import PendulumEnv

    env = PendulumEnv()
    env.reset(seed=0)
    before = env.sim.get_state()
    for action in (np.array([1 + 1j]), np.array([True]), np.array(["x"]), np.array([None], dtype=object)):
        _refused(lambda: env.step(action), "actions")
    _same(env.sim.get_state(), before)
