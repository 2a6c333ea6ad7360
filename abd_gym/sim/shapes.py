"""Shapes and their mass moments.

An affine body's 12x12 mass matrix ``M = ∫ρ J(x)ᵀ J(x) dV`` depends on the shape only through
three moments about the body origin: mass ``m`` [kg], first moment ``m·c`` [kg·m] and second
moment ``S = ∫ρ x xᵀ dV`` [kg·m²].  Each shape gives them in closed form for a uniform density;
``Inertia`` takes them from the usual rigid-body data (mass, centre of mass, inertia tensor).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import inputs


def _positive(name: str, value: float) -> float:
    """A positive finite real number (inputs.real_number)."""
    return inputs.real_number(name, value, positive=True)


@dataclass(frozen=True)
class MassMoments:
    """Mass [kg], centre of mass [m] and second moment S = ∫ρ x xᵀ dV [kg·m²] (body frame)."""

    mass: float
    com: np.ndarray
    second_moment: np.ndarray

    def scaled(self, mass: float) -> "MassMoments":
        """The same shape with total mass ``mass``: every moment scales by mass/self.mass."""
        mass = _positive("mass", mass)
        s = mass / self.mass
        return MassMoments(mass, self.com.copy(), self.second_moment * s)


def _moments_from_inertia(mass: float, com, inertia_com) -> MassMoments:
    """Second moment about the origin from the inertia tensor about the centre of mass.

    ``I = tr(Σ)·1 − Σ`` with ``Σ = ∫ρ (x−c)(x−c)ᵀ``, so ``Σ = tr(I)/2·1 − I``; then
    ``S = Σ + m c cᵀ`` (parallel axis).
    """
    c = np.asarray(com, dtype=np.float64).reshape(3)
    inertia = np.asarray(inertia_com, dtype=np.float64).reshape(3, 3)
    if not np.allclose(inertia, inertia.T, rtol=1e-9, atol=1e-12):
        raise ValueError(f"inertia tensor must be symmetric, got {inertia.tolist()}")
    sigma = 0.5 * np.trace(inertia) * np.eye(3) - inertia
    if np.linalg.eigvalsh(sigma).min() < -1e-12 * max(1.0, np.abs(inertia).max()):
        raise ValueError(f"inertia tensor violates the triangle inequality: {inertia.tolist()}")
    return MassMoments(mass, c, sigma + mass * np.outer(c, c))


class Shape:
    """A solid of uniform density centred on the body origin."""

    def volume(self) -> float:
        raise NotImplementedError

    def unit_second_moment(self) -> np.ndarray:
        """∫ x xᵀ dV / V: the second moment per unit mass [m²]."""
        raise NotImplementedError

    def bounding_radius(self) -> float:
        raise NotImplementedError

    def moments(self, mass: float | None = None, density: float = 1000.0) -> MassMoments:
        if mass is None:
            mass = _positive("density", density) * self.volume()
        mass = _positive("mass", mass)
        return MassMoments(mass, np.zeros(3), mass * self.unit_second_moment())


@dataclass(frozen=True)
class Box(Shape):
    """Box with half extents (hx, hy, hz) [m]: S/m = diag(h²)/3."""

    half_extents: tuple

    def __post_init__(self):
        h = np.array(inputs.finite_array("Box half_extents", self.half_extents, (3,)))
        for k, v in enumerate(h):
            _positive(f"Box half_extents[{k}]", v)
        object.__setattr__(self, "half_extents", tuple(h))

    def volume(self):
        return 8.0 * float(np.prod(self.half_extents))

    def unit_second_moment(self):
        return np.diag(np.square(self.half_extents) / 3.0)

    def bounding_radius(self):
        return float(np.linalg.norm(self.half_extents))


@dataclass(frozen=True)
class Sphere(Shape):
    """Sphere of radius r [m]: S/m = r²/5 · 1."""

    radius: float

    def __post_init__(self):
        _positive("Sphere radius", self.radius)

    def volume(self):
        return 4.0 / 3.0 * np.pi * self.radius**3

    def unit_second_moment(self):
        return np.eye(3) * self.radius**2 / 5.0

    def bounding_radius(self):
        return float(self.radius)


@dataclass(frozen=True)
class Cylinder(Shape):
    """Cylinder along z, radius r, half height hh [m]: S/m = diag(r²/4, r²/4, hh²/3)."""

    radius: float
    half_height: float

    def __post_init__(self):
        _positive("Cylinder radius", self.radius)
        _positive("Cylinder half_height", self.half_height)

    def volume(self):
        return np.pi * self.radius**2 * 2.0 * self.half_height

    def unit_second_moment(self):
        r2, h2 = self.radius**2, self.half_height**2
        return np.diag([r2 / 4.0, r2 / 4.0, h2 / 3.0])

    def bounding_radius(self):
        return float(np.hypot(self.radius, self.half_height))


@dataclass(frozen=True)
class Capsule(Shape):
    """Capsule along z: a cylinder (radius r, half height hh) capped by two hemispheres [m].

    The cylinder part gives ∫x² = V_c r²/4, ∫z² = V_c hh²/3; the two caps together have the
    sphere's ∫x² = V_s r²/5 and ∫z² = V_s (hh² + 3 hh r/4 + r²/5) (each hemisphere's centroid
    lies 3r/8 from its flat face at z = ±hh).
    """

    radius: float
    half_height: float

    def __post_init__(self):
        _positive("Capsule radius", self.radius)
        _positive("Capsule half_height", self.half_height)

    def volume(self):
        r, hh = self.radius, self.half_height
        return np.pi * r**2 * 2.0 * hh + 4.0 / 3.0 * np.pi * r**3

    def unit_second_moment(self):
        r, hh = self.radius, self.half_height
        vc = np.pi * r**2 * 2.0 * hh
        vs = 4.0 / 3.0 * np.pi * r**3
        # one hemisphere (volume vs/2) with its flat face at z = hh: ∫z'² about its face = (vs/2)·r²/5,
        # ∫z' = (vs/2)·3r/8, so ∫z² = ∫(hh+z')² = vs/2·(hh² + 2 hh·3r/8 + r²/5); two caps double it.
        zz = vc * hh**2 / 3.0 + vs * (hh**2 + 0.75 * hh * r + r**2 / 5.0)
        xx = vc * r**2 / 4.0 + vs * r**2 / 5.0
        return np.diag([xx, xx, zz]) / (vc + vs)

    def bounding_radius(self):
        return float(self.radius + self.half_height)


@dataclass(frozen=True)
class Inertia(Shape):
    """Explicit rigid-body data: mass [kg], centre of mass [m], inertia tensor about the com [kg·m²].

    ``size`` [m] is a length scale used for default joint spans (the shape has no extent of its own).
    """

    mass: float
    com: tuple = (0.0, 0.0, 0.0)
    inertia: tuple = ((1e-3, 0, 0), (0, 1e-3, 0), (0, 0, 1e-3))
    size: float = 0.1

    def __post_init__(self):
        _positive("Inertia mass", self.mass)
        _positive("Inertia size", self.size)
        inputs.finite_array("Inertia com", self.com, (3,))
        inputs.finite_array("Inertia inertia", self.inertia, (3, 3))

    def volume(self):
        # used only to scale the orthogonality potential: a sphere of the same size
        return 4.0 / 3.0 * np.pi * self.size**3

    def bounding_radius(self):
        return float(self.size + np.linalg.norm(self.com))

    def moments(self, mass=None, density=1000.0):
        base = _moments_from_inertia(float(self.mass), self.com, self.inertia)
        return base if mass is None else base.scaled(mass)
