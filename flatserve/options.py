"""The choices of a query and of a batch of flats, defined once.

Each is a :class:`str` enum, so its members compare equal to their values
(``Outside.NAN == "nan"``) and plain strings keep working wherever a member is
expected; the service's schemas, routes and lean query path take these
classes, and :func:`choice` is the one check of a given value.

>>> from flatserve.options import Outside, choice
>>> choice("clamp", Outside, "outside") is Outside.CLAMP
True
"""
from __future__ import annotations

from enum import Enum
from typing import TypeVar

from .errors import InvalidInputError

__all__ = ["Outside", "Order", "Interpolant", "Form", "choice"]


class Outside(str, Enum):
    """What a query outside the triangulation's convex hull answers."""

    #: NaN values, ``inside`` false (the default)
    NAN = "nan"
    #: the value interpolated on the hull facet the walk stopped at
    CLAMP = "clamp"

    def __str__(self) -> str:
        return self.value


class Order(str, Enum):
    """The order of a batch's walks through the triangulation."""

    #: sort the batch along a Hilbert curve, each walk starting at the previous answer
    HILBERT = "hilbert"
    #: the caller's order (best for coherent batches: scanlines of an image)
    GIVEN = "given"

    def __str__(self) -> str:
        return self.value


class Interpolant(str, Enum):
    """How a query's value is made from its Delaunay cell."""

    #: the paper's: the cell's values, barycentrically weighted (the default)
    LINEAR = "linear"
    #: the cell's vertices' first-order Taylor expansions, barycentrically weighted
    #: (slopes fitted to each vertex's nearest samples)
    GRADIENT = "gradient"

    def __str__(self) -> str:
        return self.value


class Form(str, Enum):
    """The four forms of a batch of flats (:data:`flatserve.flats.FORMS` names
    their arrays): rays (lines through an origin along a direction, k = 1),
    parametric ``{A y + b}``, the quadrics ``(Q, r)`` of Eq. 3 and points
    (k = 0)."""

    RAYS = "rays"
    PARAMETRIC = "parametric"
    FLATS = "flats"
    POINTS = "points"

    def __str__(self) -> str:
        return self.value


E = TypeVar("E", bound=Enum)


def choice(value, enum: type[E], argument: str) -> E:
    """``value`` as a member of ``enum``.

    Parameters
    ----------
    value : str or enum member
    enum : type
        :class:`Outside`, :class:`Order` or :class:`Form`.
    argument : str
        The name an error gives.

    Raises
    ------
    InvalidInputError
        Naming ``argument`` and the allowed values.
    """
    try:
        return enum(value)
    except ValueError:
        allowed = " or ".join(repr(m.value) for m in enum)
        raise InvalidInputError(f"{argument}: expected {allowed}, got {value!r}",
                                argument) from None
