"""The constitution protocol: what a constitution declares once, in its own module, for the staged
(reference) step and the fused step to read.

A constitution is one of three kinds:

- ``BODY``: a term per free body (affine_body);
- ``JOINT``: a term per joint of one joint kind (``joint``: revolute, prismatic or fixed);
- ``COORDINATE``: a scalar energy E(x) of a joint coordinate x (a revolute joint's angle [rad], a
  prismatic joint's displacement [m]) with its instances on joints (``instances``): limits and
  drives.  Its gradient is E′(x)∇x and its Hessian E″(x)∇x∇xᵀ (the E′∇²x part dropped, as the
  seeds do).  The fused step folds up to ``slots[kind]`` instances on one joint of that kind into
  the joint's own coordinate term (fused.terms: ``prismatic_term``, ``angle_term``), which sums
  every folded E, E′, E″ (statically, in registry order) and puts E′∇x and E″∇x∇xᵀ once; the
  instances left over keep a fused term of their own.

The staged step calls ``terms`` (its energy columns for a model) and ``launch`` (its kernel); the
lane groups weigh a term of its own by ``work``.
"""
from __future__ import annotations

import dataclasses
from types import MappingProxyType
from typing import Callable, Mapping

BODY, JOINT, COORDINATE = "body", "joint", "coordinate"


@dataclasses.dataclass(frozen=True)
class Constitution:
    """A constitution's declaration (each module's ``CONSTITUTION``, listed in ``REGISTRY``).

    ``name``: its energy column; ``uid``: the libuipc UID (None where it has none); ``kind``: BODY,
    JOINT or COORDINATE; ``reference``: its float64 NumPy reference (a tuple where it has parts: the formula the tests check
    every evaluator against); ``terms(model, physical=False)``: the staged step's energy columns
    for a model (none where the scene has no instance, so it gets no launch); ``launch(model,
    state, ctx, q, E, g, H, active, derivs, cols, physical=False)``: the staged kernel; ``work``:
    the cost of one fused term of its own in a lane group's share (thousands of cycles a
    world-step, as the phase clock counts them; Solver.lane_work).

    JOINT: ``joint``, the joint kind it constrains.

    COORDINATE: ``instances(model)``, each instance's joint (instance order); ``slots``, for each
    joint kind it sits on, how many instances on one joint the joint's term folds;
    ``fold(dtype, Terms)`` (Terms: the fused step's struct, fused.structs, which carries each
    coordinate term's fold index fields ``fold_<name>_<kind>`` and its parameters), a namespace
    with one ``wp.func`` per joint kind of ``slots``, named as the kind, that adds to the running
    E, E′, E″ of joint term a (joint j, world w) its folded instances at the joint's
    coordinate x and returns the sums:

    - ``revolute(t: Terms, w, j, a, x, hw, e, de, dde) -> (e, de, dde)``: x the step's angle
      increment δ = ΔΘ(q, q^{t−1}) [rad] (the term adds its own origin: the limit θ0, a drive the
      multi-turn angle at the step's start), hw the world's step ĥ [s];
    - ``prismatic(t: Terms, w, j, a, x, e, de, dde) -> (e, de, dde)``: x the displacement [m]
      (a term that needs ĥ reads Terms.h_step[w] where it uses it).

    It finds its instances in ``Terms.fold_<name>_<kind>`` (int32, −1 for none; (joint terms,)
    for one slot, else (joint terms, slots)), filled by the solver from terms.joint_terms.
    """

    name: str
    uid: int | None
    kind: str
    reference: Callable | tuple
    terms: Callable
    launch: Callable
    work: float = 0.0
    joint: str | None = None
    instances: Callable | None = None
    slots: Mapping[str, int] = dataclasses.field(default_factory=dict)
    fold: Callable | None = None

    def __post_init__(self):
        if self.kind not in (BODY, JOINT, COORDINATE):
            raise ValueError(f"{self.name}: kind must be body, joint or coordinate, got {self.kind!r}")
        if (self.kind == JOINT) != (self.joint is not None):
            raise ValueError(f"{self.name}: a joint constitution, and only one, names its joint kind")
        if self.kind == COORDINATE and (self.instances is None or self.fold is None or not self.slots):
            raise ValueError(f"{self.name}: a coordinate term declares instances, slots and fold")
        object.__setattr__(self, "slots", MappingProxyType(dict(self.slots)))

    def fold_field(self, joint_kind: str) -> str:
        """The Terms field of this coordinate term's instances folded on joints of ``joint_kind``."""
        return f"fold_{self.name}_{joint_kind}"
