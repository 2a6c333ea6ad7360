"""Ready-made mechanisms in their zero pose, shared by tests, benchmarks and examples.

Links hang along −z from hinges about +y (``alternating_chain``: about +y and +x in turn);
lengths in metres, masses in kilograms.
"""
import numpy as np

from .scene import Scene
from .shapes import Box


def link_shape(length, width=0.04):
    return Box(half_extents=(width / 2, width / 2, length / 2))


def chain(num_links=2, length=0.5, mass=1.0, strength_ratio=None, gravity=(0, 0, -9.81), masses=None,
          limit=None, axes=((0, 1, 0),)) -> Scene:  # fmt: skip
    """A chain of ``num_links`` links hanging from a fixed base by hinges about +y.

    ``masses`` overrides the per-link mass; ``limit=(lower, upper, strength)`` adds a revolute
    limit (UID 670) to every hinge; ``axes``: the hinges' axes, link k's ``axes[k % len(axes)]``.
    """
    scene = Scene(gravity=gravity)
    parent = scene.add_body(Box(half_extents=(0.05, 0.05, 0.05)), fixed=True, name="base")
    masses = [mass] * num_links if masses is None else masses
    for k in range(num_links):
        top = -k * length
        body = scene.add_body(link_shape(length), mass=masses[k], position=(0, 0, top - length / 2), name=f"link{k}")
        j = scene.add_revolute_joint(parent, body, anchor=(0, 0, top), axis=axes[k % len(axes)],
                                     strength_ratio=strength_ratio)  # fmt: skip
        if limit is not None:
            scene.add_revolute_limit(j, *limit)
        parent = body
    return scene


def alternating_chain(num_links=5, length=0.1, mass=1.0, **kw) -> Scene:
    """A chain whose hinges turn about +y and +x in turn (a 3-D mechanism: each link swings across
    the one above it); ``chain``'s other arguments."""
    return chain(num_links, length=length, mass=mass, axes=((0, 1, 0), (1, 0, 0)), **kw)


def mixed_masses(num_links, lightest=1e-3, heaviest=1e2) -> list:
    """Link masses [kg] spread log-evenly from ``lightest`` to ``heaviest`` and laid along a chain
    in a fixed shuffled order (heavy links beside light ones, so that joint strengths, which follow
    the masses, span the same range along the chain)."""
    m = np.geomspace(lightest, heaviest, num_links)
    return [float(x) for x in m[np.random.default_rng(num_links).permutation(num_links)]]


def pendulum(length=0.5, mass=1.0, **kw) -> Scene:
    return chain(1, length=length, mass=mass, **kw)


def double_pendulum(length=0.5, mass=1.0, **kw) -> Scene:
    return chain(2, length=length, mass=mass, **kw)


def cartpole(pole_length=1.0, pole_mass=0.1, cart_mass=1.0, track=2.4, limit_strength=1e3, force=10.0) -> Scene:
    """Cart on a slider along +x (limited to ±track), pole on a hinge about +y pointing up at zero.

    Drives: an effort drive on the slider (force [N], |u| ≤ ``force``).  ``track=None``: no limit
    on the slider; ``force=None``: no drive (the scene then compiles neither).
    """
    scene = Scene()
    rail = scene.add_body(Box(half_extents=(0.05, 0.05, 0.05)), fixed=True, name="rail")
    cart = scene.add_body(Box(half_extents=(0.2, 0.1, 0.05)), mass=cart_mass, name="cart")
    pole = scene.add_body(link_shape(pole_length, 0.02), mass=pole_mass, position=(0, 0, pole_length / 2), name="pole")
    slide = scene.add_prismatic_joint(rail, cart, anchor=(0, 0, 0), axis=(1, 0, 0))
    if track is not None:
        scene.add_prismatic_limit(slide, -track, track, limit_strength)
    scene.add_revolute_joint(cart, pole, anchor=(0, 0, 0), axis=(0, 1, 0))
    if force is not None:
        scene.add_drive(slide, mode="effort", max_effort=force)
    return scene


def slider(axis=(np.sin(np.pi / 6), 0.0, -np.cos(np.pi / 6)), mass=1.0) -> Scene:
    """A block on a prismatic joint with a fixed base; the axis is tilted 30° from −z by default."""
    scene = Scene()
    base = scene.add_body(Box(half_extents=(0.05, 0.05, 0.05)), fixed=True)
    block = scene.add_body(Box(half_extents=(0.05, 0.05, 0.05)), mass=mass)
    scene.add_prismatic_joint(base, block, anchor=(0, 0, 0), axis=axis)
    return scene
