"""The kinds of field the service tests run on (the default covering atlas, the
paper's single chart), each with the library field that must answer the same, and
the paper's ray set-up."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flatserve.atlas import Atlas
from flatserve.atlas_field import AtlasField
from flatserve.field import Field
from flatserve.flats import Flats
from flatserve.service.rooms import specs
from flatserve.service.schemas import TangentSimplexBasis

#: The paper's single chart: the tangent simplex around the z-axis, scale 0.01.
ONE_CHART = {"kind": "tangent_simplex"}


@dataclass(frozen=True)
class Kind:
    """A kind of field over HTTP and the library field that answers the same.

    Attributes
    ----------
    name : str
    basis : dict or None
        The create request's ``basis``; None: the default (a covering atlas).
    """

    name: str
    basis: dict | None

    @property
    def atlas(self) -> bool:
        """The field blends charts: every orientation accepted, no ``weights=true``."""
        return self.basis is None

    def reference(self, channels: int, k: int = 1, d: int = 3) -> "Field | AtlasField":
        """An empty library field built as the service builds this kind."""
        if self.atlas:
            return AtlasField(Atlas.covering(k, d, unit="fit"), channels=channels)  # unit: fit
        return Field(specs.build_basis(TangentSimplexBasis(**self.basis), k, d),
                     channels=channels)

    def __str__(self) -> str:
        return self.name


DEFAULT = Kind("default-atlas", None)
SINGLE = Kind("one-chart", ONE_CHART)
#: Both kinds, for tests of what must hold whatever the basis.
KINDS = [DEFAULT, SINGLE]


def add_rays(ref, o, v, values):
    """``ref.add`` of rays, for a Field or an AtlasField."""
    return ref.add(Flats.from_rays(o, v), values)


def query_rays(ref, o, v, **kw):
    """``ref.query`` of rays, for a Field or an AtlasField."""
    return ref.query(Flats.from_rays(o, v), **kw)


def paper_rays(rng: np.random.Generator, n: int):
    """The paper's ray set-up: eyes in [-1,1]^2 x [-4.5,-1.5] towards the screen z = 0."""
    eyes = rng.uniform([-1, -1, -4.5], [1, 1, -1.5], (n, 3))
    screen = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    return eyes, screen - eyes
