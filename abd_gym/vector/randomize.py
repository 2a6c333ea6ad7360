"""Domain randomisation: per-world physical parameters drawn at each reset of a world.

A spec (the vector env's ``randomize``) maps each key to a range ``(lo, hi)`` for every body or
joint it concerns, or to ``{body or joint name: (lo, hi)}`` for some of them::

    {"mass_scale": (lo, hi),              # every free body's mass × U(lo, hi) (per body)
     "strength_ratio": (lo, hi),          # every joint's strength ratio ~ U(lo, hi)
     "limit_scale": (lo, hi),             # every limit's lower and upper × U(lo, hi)
     "limit_strength_scale": (lo, hi)}    # every limit's strength × U(lo, hi)

:class:`Parameters` keeps host copies of the values in force and writes them to the simulator.
"""
from __future__ import annotations

import math

import numpy as np

from ..sim.scene import REVOLUTE

RANDOMIZE_KEYS = ("mass_scale", "strength_ratio", "limit_scale", "limit_strength_scale")


def _range(name, value):
    lo, hi = (float(v) for v in value)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise ValueError(f"randomize[{name!r}] must be a (low, high) pair with low <= high, got {value!r}")
    return lo, hi


class Parameters:
    """The per-world physical parameters of a simulator's worlds: ``body_mass`` (W, bodies) [kg],
    ``strength_ratio`` (W, joints) and ``limits`` ({limited joint index: (W, 3) lower, upper
    [rad or m], strength [J]}) as host arrays; ``spec`` the parsed randomisation in force (None:
    the nominal values); ``randomized``: whether any world's values were ever drawn (from then on
    every reset writes them, nominal ones included)."""

    def __init__(self, scene, sim):
        W = sim.num_worlds
        self.scene, self.sim = scene, sim
        self.free_bodies = [k for k, b in enumerate(scene.bodies) if not b.fixed]
        self.nominal_mass = np.array([b.mass for b in scene.bodies])
        self.nominal_ratio = scene.strength_ratios()
        self.limited = [k for k, j in enumerate(scene.joints) if j.has_limit]
        self.body_mass = np.broadcast_to(self.nominal_mass, (W, scene.num_bodies)).copy()
        self.strength_ratio = np.broadcast_to(self.nominal_ratio, (W, scene.num_joints)).copy()
        attrs = ("limit/lower", "limit/upper", "limit/strength")
        self.limits = {k: np.broadcast_to([scene.joints[k].attributes[a] for a in attrs], (W, 3)).copy()
                       for k in self.limited}  # fmt: skip
        self.spec = None
        self.randomized = False

    @property
    def active(self) -> bool:
        """Whether resets write parameters (a spec is in force, or one was)."""
        return self.spec is not None or self.randomized

    def set_spec(self, spec):
        """Parse and check a randomisation spec (module docstring); None or {}: nominal values."""
        if spec is None or spec == {}:
            self.spec = None
            return
        if not isinstance(spec, dict):
            raise ValueError(f"randomize must be a dict or None, got {spec!r}")
        unknown = set(spec) - set(RANDOMIZE_KEYS)
        if unknown:
            raise ValueError(f"unknown randomize keys {sorted(unknown)}; known: {list(RANDOMIZE_KEYS)}")
        self.spec = {key: self._ranges(key, value) for key, value in spec.items()}

    def _ranges(self, key, value) -> dict:
        """{body or joint index: (lo, hi)} of one spec entry."""
        scene = self.scene
        if key == "mass_scale":
            names, to_index = self.free_bodies, scene.body_index
        elif key == "strength_ratio":
            names, to_index = list(range(scene.num_joints)), scene.joint_index
        else:
            names, to_index = self.limited, scene.joint_index
        if isinstance(value, dict):
            ranges = {}
            for name, r in value.items():
                k = to_index(name)
                if k not in names:
                    raise ValueError(f"randomize[{key!r}]: {name!r} cannot be randomised (fixed body or no limit)")
                ranges[k] = _range(key, r)
        else:
            r = _range(key, value)
            ranges = {k: r for k in names}
        if key != "limit_scale" and any(lo <= 0 for lo, _ in ranges.values()):
            raise ValueError(f"randomize[{key!r}] ranges must be positive, got {value!r}")
        return ranges

    def apply(self, idx: np.ndarray, rng: np.random.Generator):
        """Draw (or restore) the parameters of the worlds ``idx`` and write them to the simulator."""
        self.write(idx, self.draw(idx, rng))

    def draw(self, idx: np.ndarray, rng: np.random.Generator) -> dict | None:
        """The parameters of the worlds ``idx`` for a reset, drawn (or nominal), written nowhere:
        {"mass": (n, free bodies), "ratio": (n, joints) or None, "limits": {limited joint: (lower,
        upper, strength), each (n,)}}; None where resets write no parameters (``active``)."""
        spec = self.spec
        if spec is None and not self.randomized:
            return None
        spec = spec or {}
        n, scene = len(idx), self.scene

        def draw(key, k, nominal):
            r = spec.get(key, {}).get(k)
            return np.full(n, nominal) if r is None else rng.uniform(r[0], r[1], size=n)

        mass = np.stack([self.nominal_mass[k] * draw("mass_scale", k, 1.0) for k in self.free_bodies], axis=1)
        ratio = None
        if scene.num_joints:
            ratio = np.stack([draw("strength_ratio", k, r) for k, r in enumerate(self.nominal_ratio)], axis=1)
        limits = {}
        for k in self.limited:
            j = scene.joints[k]
            lo, up, st = (j.attributes[f"limit/{a}"] for a in ("lower", "upper", "strength"))
            f = draw("limit_scale", k, 1.0)
            lo_k, up_k = np.minimum(lo * f, up * f), np.maximum(lo * f, up * f)
            if j.kind == REVOLUTE:
                lo_k, up_k = np.clip(lo_k, -math.pi, math.pi), np.clip(up_k, -math.pi, math.pi)
            limits[k] = (lo_k, up_k, st * draw("limit_strength_scale", k, 1.0))
        return {"mass": mass, "ratio": ratio, "limits": limits}

    def check(self, idx: np.ndarray, drawn: dict | None):
        """The simulator's checks of ``draw``'s values for the worlds ``idx`` (those its setters
        make: finite, within bounds, positive, ordered bounds), a ValueError naming the world and
        the item; nothing is written.  The states that the limits must hold are checked apart
        (Simulator.check_joint_state with these limits)."""
        if drawn is None:
            return
        sim = self.sim
        sim.check_body_mass(drawn["mass"], bodies=self.free_bodies, worlds=idx)
        if drawn["ratio"] is not None:
            sim.check_joint_strength(drawn["ratio"], worlds=idx)
        for k, (lo_k, up_k, st_k) in drawn["limits"].items():
            sim.check_limit(k, lower=lo_k, upper=up_k, strength=st_k, worlds=idx, check_state=False)

    def write(self, idx: np.ndarray, drawn: dict | None):
        """``draw``'s values of the worlds ``idx`` into the values in force and the simulator
        (``check``ed first by the caller that must write all or nothing)."""
        if drawn is None:
            return
        self.randomized = True
        sim, free = self.sim, self.free_bodies
        self.body_mass[np.ix_(idx, free)] = drawn["mass"]
        sim.set_body_mass(drawn["mass"], bodies=free, worlds=idx)
        if drawn["ratio"] is not None:
            self.strength_ratio[idx] = drawn["ratio"]
            sim.set_joint_strength(drawn["ratio"], worlds=idx)
        for k, (lo_k, up_k, st_k) in drawn["limits"].items():
            self.limits[k][idx] = np.stack([lo_k, up_k, st_k], axis=1)
            sim.set_limit(k, lower=lo_k, upper=up_k, strength=st_k, worlds=idx, check_state=False)  # states set next

    def snapshot(self) -> dict:
        """The values in force and the spec, as host values."""
        return {"spec": self.spec, "randomized": self.randomized, "body_mass": self.body_mass.copy(),
                "strength_ratio": self.strength_ratio.copy(), "limits": {k: v.copy() for k, v in self.limits.items()}}

    def check_snapshot(self, snap: dict):
        """Refuse (ValueError naming the entry) values ``restore`` could not write whole: other
        entries or shapes than ``snapshot``'s, masses and strengths not positive and finite,
        limits not finite with lower <= upper."""
        mine = self.snapshot()
        if not isinstance(snap, dict) or set(snap) != set(mine):
            raise ValueError(f"state['parameters'] must hold the entries {sorted(mine)}")
        if not isinstance(snap["limits"], dict) or set(snap["limits"]) != set(mine["limits"]):
            raise ValueError(f"state['parameters']['limits'] must hold the limited joints {sorted(mine['limits'])}")
        arrays = [("['body_mass']", snap["body_mass"], mine["body_mass"]),
                  ("['strength_ratio']", snap["strength_ratio"], mine["strength_ratio"])]
        arrays += [(f"['limits'][{k!r}]", snap["limits"][k], v) for k, v in mine["limits"].items()]
        for name, v, ref in arrays:
            if not isinstance(v, np.ndarray) or v.shape != ref.shape or v.dtype != ref.dtype:
                raise ValueError(f"state['parameters']{name} must be {ref.dtype} of shape {ref.shape}")
            if not np.all(np.isfinite(v)):
                raise ValueError(f"state['parameters']{name} must be finite")
        if (snap["body_mass"][:, self.free_bodies] <= 0).any() or (snap["strength_ratio"] <= 0).any():
            raise ValueError("state['parameters']: masses and strength ratios must be positive")
        for k, v in snap["limits"].items():
            if (v[:, 0] > v[:, 1]).any() or (v[:, 2] <= 0).any():
                raise ValueError(f"state['parameters']['limits'][{k!r}]: lower must not exceed upper, "
                                 f"strength must be positive")

    def restore(self, snap: dict):
        """``snapshot``'s values back, and into the simulator, every world at once, where they were
        ever drawn (the setters compute from the nominal values, so the model arrays come out as
        the original's)."""
        was = self.randomized  # (values drawn before: the simulator holds them until written back)
        self.spec, self.randomized = snap["spec"], snap["randomized"]
        self.body_mass, self.strength_ratio, self.limits = snap["body_mass"], snap["strength_ratio"], snap["limits"]
        if not (was or self.randomized):
            return
        sim, free = self.sim, self.free_bodies
        sim.set_body_mass(self.body_mass[:, free], bodies=free)
        if self.scene.num_joints:
            sim.set_joint_strength(self.strength_ratio)
        for k, values in self.limits.items():
            sim.set_limit(k, lower=values[:, 0], upper=values[:, 1], strength=values[:, 2], check_state=False)
