"""flatserve: compute with flats (affine subspaces) the way you compute with points.

Public API
----------
flats         (Q, r) flats: constructors, conversions, projection, affine combinations
Flats         a batch of flats in any form (rays, parametric, quadrics), validated once
Basis         a basis of flats, its checks, the tangent simplex, coordinates
coordinates   coordinates of flats in a basis (paper Sec. 4), status codes
embedding     the regular-simplex embedding of affine coordinates (Sec. 5)
Triangulation CGAL dD Delaunay triangulation with scipy's vocabulary
Field         a function sampled on flats: basis + triangulation + values
grassmann     principal angles, frames, coverings of the Grassmannian, the blending bump
Atlas         charts covering every orientation (covering or data-driven)
AtlasField    a function sampled on flats over an atlas: a Field per chart, blended
SampledField  the contract both kinds of field offer; new_field, load_field,
              describe_definition make, read and describe either kind
errors        the one error hierarchy
"""
from __future__ import annotations

from . import coordinates, embedding, errors, flats, grassmann
from .atlas import Atlas
from .atlas_field import AtlasField
from .basis import Basis, select_scale
from .contract import SampledField, describe_definition, load_field, new_field
from .field import AddResult, Chart, Field, QueryResult
from .flats import Flats
from .triangulation import Triangulation

__version__ = "0.1.0"

__all__ = [
    "AddResult",
    "Atlas",
    "AtlasField",
    "Basis",
    "Chart",
    "Field",
    "Flats",
    "QueryResult",
    "SampledField",
    "Triangulation",
    "coordinates",
    "describe_definition",
    "embedding",
    "errors",
    "flats",
    "grassmann",
    "load_field",
    "new_field",
    "select_scale",
]
