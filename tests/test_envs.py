"""The registered tasks: API checkers, reward ranges, scripted vs random policies, physics invariants.

Few worlds, short rollouts; the rollouts of each task are made once (module scope) and shared.
"""
import importlib
import inspect
import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import abd_gym  # noqa: F401 -- registers the ids
from abd_gym.vector.registration import TASKS

N = 4
IDS = [f"abd_gym/{name}" for name in TASKS]
# env steps of the shared rollouts (long enough for the scripted controllers to show)
ROLLOUT_STEPS = {"Pendulum-v0": 100, "Acrobot-v0": 300, "TwoLinkReacher-v0": 50}  # Acrobot: the scripted swing-up takes 60-231 steps


def module_of(env_id):
    return importlib.import_module(TASKS[env_id.split("/")[1]][0])


def vector_class(env_id):
    return getattr(module_of(env_id), TASKS[env_id.split("/")[1]][2])


def scripted_actions(mod, env, obs):
    if "env" in inspect.signature(mod.scripted_policy).parameters:
        return mod.scripted_policy(env)
    return mod.scripted_policy(obs)


_ROLLOUTS = {}


def rollout(env_id, policy):
    """(rewards (T, N), terminated (T, N), observations (T, N, d), env) of a SAME_STEP run, cached."""
    key = (env_id, policy)
    if key not in _ROLLOUTS:
        mod, name = module_of(env_id), env_id.split("/")[1]
        env = vector_class(env_id)(N, autoreset_mode=AutoresetMode.SAME_STEP, max_episode_steps=TASKS[name][3])
        obs, _ = env.reset(seed=0)
        rng = np.random.default_rng(0)
        rewards, terms, observations = [], [], [obs]
        for _ in range(ROLLOUT_STEPS.get(name, 100)):
            a = scripted_actions(mod, env, obs) if policy == "scripted" else rng.uniform(-1, 1, (N, env.action_dim))
            obs, r, te, tr, info = env.step(a)
            rewards.append(r)
            terms.append(te)
            observations.append(obs)
            if "final_obs" in info:
                observations.append(info["final_obs"][info["_final_obs"]])
        _ROLLOUTS[key] = (np.array(rewards), np.array(terms), observations, env)
    return _ROLLOUTS[key]


# ----------------------------------------------------------------------------- API checkers
def fail_on_checker_warnings(env):
    """A checker warning fails the test, except both checkers' advice to normalise the action range
    for a task whose range is its source's (InvertedPendulum-v5: Gymnasium's Box(-3, 3))."""
    warnings.simplefilter("error")
    if np.any(env.action_space.high != 1.0):
        warnings.filterwarnings("ignore", message=".*symmetric and normalized")


@pytest.mark.parametrize("env_id", IDS)
def test_gymnasium_check_env(env_id):
    from gymnasium.utils.env_checker import check_env

    env = gym.make(env_id, render_mode="rgb_array")
    with warnings.catch_warnings():
        fail_on_checker_warnings(env)
        check_env(env.unwrapped)
    env.close()


@pytest.mark.parametrize("env_id", IDS)
def test_sb3_check_env(env_id):
    from stable_baselines3.common.env_checker import check_env

    env = gym.make(env_id)
    with warnings.catch_warnings():
        fail_on_checker_warnings(env)
        check_env(env.unwrapped)
    env.close()


@pytest.mark.parametrize("env_id", IDS)
def test_single_env_render(env_id):
    env = gym.make(env_id, render_mode="rgb_array")
    env.reset(seed=0)
    env.step(env.action_space.sample())
    frame = env.render()
    w, h = vector_class(env_id).render_size
    assert frame.dtype == np.uint8 and frame.shape == (h, w, 3)
    drawn = (frame != 255).any(axis=2).mean()
    assert 0.002 < drawn < 0.5
    env.close()


# ----------------------------------------------------------------------------- rewards
@pytest.mark.parametrize("policy", ["random", "scripted"])
@pytest.mark.parametrize("env_id", IDS)
def test_rewards_in_documented_range_and_obs_in_space(env_id, policy):
    lo, hi = module_of(env_id).REWARD_RANGE
    rewards, _, observations, env = rollout(env_id, policy)
    assert rewards.dtype == np.float32
    assert rewards.min() >= lo - 1e-5 and rewards.max() <= hi + 1e-5, (rewards.min(), rewards.max())
    space = env.single_observation_space
    for obs in observations:
        for o in obs:
            assert space.contains(o), o


@pytest.mark.parametrize("env_id", IDS)
def test_scripted_policy_beats_random(env_id):
    name = env_id.split("/")[1]
    r_s, t_s, _, _ = rollout(env_id, "scripted")
    r_r, t_r, _, _ = rollout(env_id, "random")
    if name in ("CartPole-v0", "DoublePendulumCart-v0"):  # reward is (mostly) 1 per step: compare episode ends
        assert t_s.sum() == 0 and t_r.sum() >= N
    else:
        lo, hi = module_of(env_id).REWARD_RANGE
        assert r_s.mean() - r_r.mean() > 0.1 * min(hi - lo, 1.0), (r_s.mean(), r_r.mean())


def test_acrobot_reaches_the_goal_with_the_scripted_policy():
    rewards, terms, _, _ = rollout("abd_gym/Acrobot-v0", "scripted")
    assert terms.any(axis=0).all()  # every world swung its tip above the line
    assert np.all(rewards[terms] == 0.0)


# ----------------------------------------------------------------------------- physics invariants
def test_pendulum_energy_sanity():
    from abd_gym.envs.pendulum import PendulumVectorEnv

    env = PendulumVectorEnv(2, autoreset_mode=AutoresetMode.DISABLED, integrator="implicit_euler")
    env.reset(seed=0)
    env.sim.set_joint_state([[math.pi - 0.5], [math.pi - 0.5]])  # 0.5 rad from hanging, at rest
    e0 = env.sim.energies()
    E0 = e0["kinetic"] + e0["gravity"]
    torque = np.array([[0.0], [0.5]], dtype=np.float32)  # world 1 pushed with 1 N·m
    E, work, theta_prev = [], np.zeros(2), env.sim.joint_angles_unwrapped()[:, 0]
    for _ in range(60):
        obs, *_ = env.step(torque)
        theta = env.sim.joint_angles_unwrapped()[:, 0]
        work += torque[:, 0] * env.max_torque * (theta - theta_prev)
        theta_prev = theta
        e = env.sim.energies()
        E.append(e["kinetic"] + e["gravity"] - work)
        # the observation is the rod's orientation: cos θ = z-component of the rod's axis
        np.testing.assert_allclose(obs[:, 0], env.sim.body_rotations()[:, 1, 2, 2], atol=1e-4)
    E = np.array(E)
    amplitude = 9.81 * 0.5 * (1 - math.cos(0.5))  # m g l/2 (1 − cos 0.5) [J]
    # implicit Euler only removes energy: never more than the start plus the motor's work
    assert np.all(E <= E0 + 1e-3 * amplitude)
    # ...at the rate implicit Euler damps an oscillator: energy × 1/(1 + ω²h²) per step, about half
    # of the swing's energy in 120 steps of 0.02 s (ω² = m g l/2 / I about the pivot)
    omega2 = 9.81 * 0.5 / (1.0 / 3 + 0.04**2 / 12)
    predicted = (1 + omega2 * env.dt**2) ** -120
    remaining = (E[-1, 0] - (-9.81 * 0.5)) / amplitude  # swing energy over the hanging rest state
    assert abs(remaining - predicted) < 0.15, (remaining, predicted)
    theta = env.sim.joint_coordinates()[0, 0]
    assert abs(abs(theta) - math.pi) <= 0.5 + 1e-3


def test_cart_stays_within_its_track_limits():
    from abd_gym.envs.cartpole_swingup import CartPoleSwingUpVectorEnv

    env = CartPoleSwingUpVectorEnv(2, autoreset_mode=AutoresetMode.DISABLED)
    env.reset(seed=0)
    push = np.array([[1.0], [-1.0]], dtype=np.float32)  # full force into each end stop
    xs = []
    for _ in range(150):
        obs, _, te, _, _ = env.step(push)
        xs.append(obs[:, 0])
        assert not te.any()
    xs = np.array(xs)
    assert xs[:, 0].max() > 2.3 and xs[:, 1].min() < -2.3  # the cart got to the end stops...
    assert np.abs(xs).max() < 2.4 + 0.05  # ...and they held it
    assert env.sim.joint_violation().max() < 1e-3


def test_cartpole_termination_at_the_track_end():
    from abd_gym.envs.cartpole import CartPoleVectorEnv

    env = CartPoleVectorEnv(1, autoreset_mode=AutoresetMode.DISABLED)
    env.reset(seed=0)
    env.sim.set_joint_state([[2.3, 0.0]], [[3.0, 0.0]])  # heading for the end at 3 m/s, pole upright
    for _ in range(10):
        obs, _, te, _, _ = env.step(np.zeros((1, 1)))
        if te[0]:
            break
    assert te[0] and obs[0, 0] > 2.4 and abs(obs[0, 2]) < 0.2


def test_double_pendulum_tip_height_matches_the_bodies():
    rewards, terms, _, env = rollout("abd_gym/DoublePendulumCart-v0", "random")
    obs, _ = env.reset(seed=3)
    rng = np.random.default_rng(1)
    for _ in range(15):
        obs, _, te, _, _ = env.step(rng.uniform(-1, 1, (N, 1)))
        p, A = env.sim.body_positions(), env.sim.body_rotations()
        tip_z = p[:, 3, 2] + A[:, 3, 2, 2] * env.pole_lengths[1] / 2  # top of pole 2
        np.testing.assert_allclose(env.tip_height(obs) * env.height, tip_z, atol=2e-3)
        np.testing.assert_array_equal(te, (tip_z / env.height < 0.8) | (np.abs(obs[:, 0]) > 2.4))


def test_acrobot_elbow_limit_holds_and_can_be_randomised():
    from abd_gym.envs.acrobot import AcrobotVectorEnv

    env = AcrobotVectorEnv(2, autoreset_mode=AutoresetMode.DISABLED)
    env.reset(seed=0)
    env.reset(options={"reset_mask": np.array([False, True]), "randomize": {"limit_scale": (0.5, 0.5)}})
    np.testing.assert_allclose(env.limits[1][:, 1], [2.5, 1.25])  # world 1: elbow limited to ±1.25 rad
    elbow, tip = [], []
    for _ in range(40):
        obs, *_ = env.step(np.ones((2, 1), dtype=np.float32))  # full elbow torque, one way
        elbow.append(env.sim.joint_coordinates()[:, 1])
        p, A = env.sim.body_positions(), env.sim.body_rotations()
        tip.append((p[:, 2, 2] - A[:, 2, 2, 2] * 0.5, env.tip_height(obs)))
    elbow = np.array(elbow)
    assert elbow[:, 0].max() > 2.3 and elbow[:, 0].max() < 2.5 + 0.05
    assert elbow[:, 1].max() > 1.1 and elbow[:, 1].max() < 1.25 + 0.05
    for from_bodies, from_obs in tip:
        np.testing.assert_allclose(from_obs, from_bodies, atol=2e-3)


def test_reacher_target_reset_option_and_mask():
    """TwoLinkReacher-v0's target (its task_state): the reset option ``target`` fixes it for the worlds
    reset, a masked reset redraws only the masked worlds' targets, and the observation carries
    the target as held."""
    from abd_gym.envs.reacher import ReacherVectorEnv

    env = ReacherVectorEnv(3, autoreset_mode=AutoresetMode.DISABLED)
    obs, _ = env.reset(seed=1, options={"target": (0.1, -0.05)})
    np.testing.assert_array_equal(env.target, np.float32([[0.1, -0.05]] * 3))
    np.testing.assert_array_equal(obs[:, 4:6], env.target)
    before = np.array(env.target)
    obs, _ = env.reset(options={"reset_mask": np.array([False, True, False])})
    assert not np.array_equal(env.target[1], before[1])
    np.testing.assert_array_equal(env.target[[0, 2]], before[[0, 2]])
    assert 0.03 - 1e-6 <= np.hypot(*env.target[1]) <= 0.2 + 1e-6
    np.testing.assert_array_equal(obs[:, 4:6], env.target)
    env.close()


def test_reacher_shoulder_limit_near_180_degrees():
    from abd_gym.envs.reacher import ReacherVectorEnv

    env = ReacherVectorEnv(2, autoreset_mode=AutoresetMode.DISABLED)
    env.reset(seed=0)
    q = []
    for _ in range(40):
        obs, *_ = env.step(np.array([[1.0, 0.0], [-1.0, 0.0]], dtype=np.float32))
        q.append(env.sim.joint_coordinates()[:, 0])
        p, A = env.sim.body_positions(), env.sim.body_rotations()
        tip = p[:, 2, :2] + A[:, 2, :2, 0] * env.lengths[1] / 2
        np.testing.assert_allclose(obs[:, 8:10] + obs[:, 4:6], tip, atol=2e-3)  # tip − target + target
    q = np.array(q)
    assert q[:, 0].max() > 2.9 and q[:, 1].min() < -2.9  # swung round to the stops at ±175°...
    assert q[:, 0].max() < 3.05 + 0.05 and q[:, 1].min() > -3.05 - 0.05  # ...and not through them


def test_fourbar_loop_stays_closed_under_bdf2():
    """The closed loop under BDF2 (whose first step after each reset is implicit Euler)."""
    env = vector_class("abd_gym/FourBar-v0")(N, integrator="bdf2")
    env.reset(seed=4)
    rng = np.random.default_rng(4)
    for _ in range(40):
        env.step(rng.uniform(-1, 1, (N, 1)))
        assert env.sim.joint_violation().max() < 1e-3
    assert env.sim.converged().all() and not env.sim.failed_worlds().size
    env.close()


def test_fourbar_loop_stays_closed():
    _, _, _, env = rollout("abd_gym/FourBar-v0", "random")
    env.reset(seed=4)
    assert env.sim.joint_violation().max() < 1e-5  # the reset state closes the loop
    rng = np.random.default_rng(4)
    for _ in range(40):
        env.step(rng.uniform(-1, 1, (N, 1)))
        assert env.sim.joint_violation().max() < 1e-3
        # the coupler point from the coupler body's pose lies where the loop's kinematics put it
        phi = env.sim.joint_coordinates()[:, 0] + env.phi_ref
        _, _, (px, pz) = env.points(np, phi)
        np.testing.assert_allclose(env.coupler_point_position(), np.stack([px, pz], 1), atol=2e-3)


def test_slider_crank_loop_and_piston_limits():
    from abd_gym.envs.slider_crank import piston_x

    _, _, _, env = rollout("abd_gym/SliderCrank-v0", "random")
    env.reset(seed=0)
    lo, hi = env.stroke
    push = np.array([[1.0], [-1.0], [1.0], [-1.0]], dtype=np.float32)  # full torque both ways
    s = []
    for _ in range(60):
        env.step(push)
        assert env.sim.joint_violation().max() < 1e-3
        q = env.sim.joint_coordinates()
        s.append(q[:, 3])
        np.testing.assert_allclose(q[:, 3], piston_x(np, q[:, 0] + env.phi_ref, env.r, env.L) - env.x_ref, atol=1e-3)
    s = np.array(s)
    assert s.min() < lo + 0.01 and s.max() > hi - 0.01  # the piston is driven into both limits...
    assert s.min() > lo - 0.005 and s.max() < hi + 0.005  # ...which hold it short of the dead centres


def test_fourbar_target_velocity_is_the_targets_rate():
    """The observed Ṗ* is dP*/dt of the target's own curve: against a float64 central difference of
    step 1e-6 s (error ~1e-9 m/s), to float32 rounding of the observation (|Ṗ*| < ~1 m/s)."""
    from abd_gym.envs.fourbar import fourbar_points

    env = rollout("abd_gym/FourBar-v0", "random")[3]
    a, b, c, d = env.lengths
    env.reset(seed=6)
    for _ in range(5):
        obs = env.step(np.full((N, 1), 0.5))[0]
    phase = np.asarray(env.target_phase(), dtype=np.float64)
    h, w = 1e-6, np.asarray(env.target_speed, dtype=np.float64)
    _, _, (x1, z1) = fourbar_points(np, phase + w * h, a, b, c, d, env.coupler_point)
    _, _, (x0, z0) = fourbar_points(np, phase - w * h, a, b, c, d, env.coupler_point)
    rate = np.stack([x1 - x0, z1 - z0], axis=1) / (2 * h)
    assert np.abs(rate).max() > 0.05  # the targets move
    np.testing.assert_allclose(obs[:, 7:9], rate, rtol=0, atol=2e-6)


@pytest.mark.parametrize("env_id", ["abd_gym/FourBar-v0", "abd_gym/SliderCrank-v0"])
def test_linkage_targets_move(env_id):
    _, _, observations, env = rollout(env_id, "random")
    track = np.array([o[:, 5] for o in observations[:20]])  # P*_x for the four-bar, s* for the slider-crank
    assert np.ptp(track, axis=0).min() > 1e-3


def test_pendulum_default_integrator_keeps_its_swing():
    """Pendulum-v0 with the default integrator (BDF2), released from horizontal at zero torque:
    its swing energy ½Iθ̇² + m g (l/2) cos θ starts at 0 and stays above −0.5 J after 100 env steps
    (4 s; the hanging rest state is −4.9 J, where implicit Euler's damping takes it: −4.0 J)."""
    from abd_gym.envs.pendulum import PendulumVectorEnv

    env = PendulumVectorEnv(1, autoreset_mode=AutoresetMode.DISABLED)
    env.reset(seed=0)
    env.sim.set_joint_state([[math.pi / 2]])
    inertia = (1.0 + 0.04**2) / 12 + 0.25  # about the pivot [kg·m²]
    for _ in range(100):
        obs, *_ = env.step(np.zeros((1, 1), np.float32))
    swing = 0.5 * inertia * float(obs[0, 2]) ** 2 + 9.81 * 0.5 * float(obs[0, 0])
    assert -0.5 < swing <= 1e-3, swing
