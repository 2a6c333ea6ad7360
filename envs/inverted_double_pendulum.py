"""InvertedDoublePendulum-v5: Gymnasium's MuJoCo double pendulum on a cart, built from its own
``inverted_double_pendulum.xml``.

Scene: the file as MuJoCo compiles it (``Scene.from_mjcf``): a cart (10.47 kg) on the slider
  ``slider`` along +x, range ±1 m; two poles (4.20 kg, 0.6 m capsules) on the hinges ``hinge``
  (cart–pole) and ``hinge2`` (pole–pole) about +y, unlimited; damping 0.05 on every joint;
  gravity (1e-5, 0, −9.81) m/s².  The site ``tip`` sits 0.6 m up the second pole.  The motor
  ``slide`` (gear 500) pushes the cart.
Coordinates: MuJoCo's qpos: x [m] cart, θ1 [rad] pole 1 from upright, θ2 [rad] pole 2 relative to
  pole 1 (positive tipping towards +x).
Action: Box(-1, 1, (1,)) (the motor's ctrlrange): the cart force u = 500 · a [N].
Observation: Box(9,) float32 [x, sin θ1, sin θ2, cos θ1, cos θ2, clip(ẋ, θ̇1, θ̇2; ±10),
  clip(f_limit; ±10)]; bounds ±(2, 1, 1, 1, 1, 10, 10, 10, 10): beyond the slider's range, then
  Gymnasium's own clips (Gymnasium: float64, ±inf).  f_limit [N] is Gymnasium's
  ``qfrc_constraint[0]``, the generalised force of the slider's limit on x: here −E'(x)/h² of
  abd_gym's limit penalty E [J·s²] (zero inside the range, pushing back beyond it) at the observed
  state;
  MuJoCo's is the soft constraint's force of its last solve, which its margin (0.01 m) turns on
  just inside the range and whose impedance sets its size, so the two agree in sign and in being
  zero away from the ends, not in value at the ends.
Reward: r = 10·[y > 1] − (0.01 x_t² + (y − 2)²) − (0.001 θ̇1² + 0.005 θ̇2²), (x_t, y) the tip's
  x and z [m], rates unclipped: 9.36 at most (upright, y = 1.2); a step that ends the episode
  loses the 10; with rates under ~10 rad/s, per step in [−12, 9.36]; episode return at most
  9,360.
Termination: the tip's height y ≤ 1 m.  Truncation at 1000 steps; ``reward_threshold`` 9100.
Reset: qpos ~ U(−0.1, 0.1), qvel ~ 0.1·N(0, 1) each (``reset_noise_scale``).
Step: dt = 0.01 s (the file's timestep), frame_skip 5 (0.05 s, 20 Hz).

Differs from Gymnasium: the physics (abd_gym's affine bodies and implicit BDF2 against MuJoCo's
RK4), the limit force entry (above), float32 observations with finite bounds, and the reset
draws (abd_gym's generator: same distributions, another stream).
"""
from __future__ import annotations

import numpy as np

from abd_gym.vector.vector_env import ABDEnv

from abd_gym.envs.gymnasium_mjcf import GymnasiumMjcfEnv
from abd_gym.envs.inverted_pendulum import draw_rail

REWARD_RANGE = (-12.0, 9.36)  # per step

# LQR gains on (x, θ1, θ2, ẋ, θ̇1, θ̇2) of MuJoCo's linearisation at upright, a = −K·s (ctrl units)
LQR_GAINS = np.array([0.0834, 1.2602, 5.209, 0.1684, 0.7171, 0.7644])


class InvertedDoublePendulumVectorEnv(GymnasiumMjcfEnv):
    """Batched InvertedDoublePendulum-v5 (see the module docstring)."""

    asset = "inverted_double_pendulum.xml"
    dt, frame_skip = 0.01, 5
    render_center, render_width, render_size = (0.0, 0.4), 3.6, (600, 450)
    clip = 10.0  # Gymnasium's clip of the rates and the limit force
    healthy_height = 1.0  # m: the tip above it, the episode goes on

    def __init__(self, num_envs=1, *, healthy_reward=10.0, reset_noise_scale=0.1, **kwargs):
        self.healthy_reward, self.reset_noise_scale = healthy_reward, reset_noise_scale
        super().__init__(num_envs, **kwargs)

    def build_scene(self):
        scene = super().build_scene()
        a = scene.joints[0].attributes  # the slider's limit, as imported
        self.slider_limit = (a["limit/lower"], a["limit/upper"], a["limit/strength"])
        return scene

    def observation_high(self):
        return np.array([2.0, 1, 1, 1, 1, self.clip, self.clip, self.clip, self.clip])

    def initial_state(self, n, rng, options):
        s = self.reset_noise_scale
        return rng.uniform(-s, s, size=(n, 3)), s * rng.standard_normal(size=(n, 3))

    def limit_force(self, x):
        """(N,) generalised force of the slider's limit [N] at cart positions x (N,): −E'(x)/h².  The
        limit is a penalty of the incremental potential, E = s((x − u)/w)³ beyond u (mirrored below
        l, w = u − l) in J·s² (docs/design.md §2.1, §3.3), and the steps where it acts are implicit
        Euler steps of h = dt.  The scene's nominal limit (randomised limits are not followed)."""
        xp = self.xp
        lower, upper, strength = self.slider_limit
        w = upper - lower
        over = xp.clip(x - upper, 0.0, None) / w
        under = xp.clip(lower - x, 0.0, None) / w
        return 3.0 * strength / (w * self.dt**2) * (under**2 - over**2)

    def observe(self):
        xp, q, v = self.xp, self.coords(), self.velocities()
        f = self.limit_force(q[:, 0])
        return xp.concatenate([q[:, :1], xp.sin(q[:, 1:]), xp.cos(q[:, 1:]), xp.clip(v, -self.clip, self.clip),
                               xp.clip(f, -self.clip, self.clip)[:, None]], axis=1)  # fmt: skip

    def tip(self):
        """(N, 2) the site ``tip``'s x and z [m]."""
        p = self.frame_point("tip", site=True)
        return self.xp.stack([p[:, 0], p[:, 2]], axis=1)  # no index list: a host array, which a CUDA graph cannot hold

    def terminated(self, obs):
        return self.tip()[:, 1] <= self.healthy_height

    def reward(self, obs, actions):
        tip, v = self.tip(), self.velocities()
        alive = self.healthy_reward * self.f32(tip[:, 1] > self.healthy_height)
        distance = 0.01 * tip[:, 0] ** 2 + (tip[:, 1] - 2.0) ** 2
        rates = 0.001 * v[:, 1] ** 2 + 0.005 * v[:, 2] ** 2
        return alive - distance - rates

    def render_extras(self, canvas, world):
        draw_rail(canvas)


class InvertedDoublePendulumEnv(ABDEnv):
    """Single-world InvertedDoublePendulum-v5."""

    vector_class = InvertedDoublePendulumVectorEnv


def scripted_policy(obs):
    """LQR balancer a = −K·(x, θ1, θ2, ẋ, θ̇1, θ̇2), clipped to ±1, for observations (N, 9)."""
    obs = np.asarray(obs, dtype=np.float64)
    theta = np.arctan2(obs[:, 1:3], obs[:, 3:5])
    s = np.concatenate([obs[:, :1], theta, obs[:, 5:8]], axis=1)
    return np.clip(-s @ LQR_GAINS, -1.0, 1.0)[:, None].astype(np.float32)
