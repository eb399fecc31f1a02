"""Pydantic models of the small JSON documents a client sends (field definitions,
request bodies); the answers are :mod:`.reports`.

Bulk arrays (upload and query bodies) are NOT parsed through these models: the
``*Body`` models below only document the JSON form in OpenAPI; the service
decodes them with orjson + NumPy (see :mod:`.http.codec`).
"""
from __future__ import annotations

from typing import Annotated, ClassVar, Literal, Optional, Union

from pydantic import (BaseModel, ConfigDict, Discriminator, Field, Tag, ValidationError,
                      field_validator, model_validator)

from ..atlas_field import FIT_MIN_ROWS
from ..flats import FORMS, basis_size
from ..options import Form
from .settings import FIELD_NAME_PATTERN

Vec = list[float]
Mat = list[list[float]]
Mats = list[list[list[float]]]
#: A batch's per-row array, (n, W) or (n, a, b): every batch has at least one row.
#: Said in the schema only (``minItems``); the service's decoder (:mod:`.http.codec`,
#: :class:`flatserve.flats.Flats`) refuses an empty one, naming the array.
Rows = Annotated[Mat, Field(json_schema_extra={"minItems": 1})]
RowMats = Annotated[Mats, Field(json_schema_extra={"minItems": 1})]

#: ``min_position`` of a read (a query parameter of describe and query)
MIN_POSITION_DESCRIPTION = (
    "Read-your-writes: answer only once this replica has applied the log position a write "
    "returned (`position` of an upload, or the `Flatserve-Position` header of any write), "
    "waiting up to `read_wait_timeout` seconds; then 503 with `Retry-After` (any replica "
    "answers it; one behind waits). A position beyond the log's last one (describe's or "
    "`/readyz`' `head`) was never returned by a write: 422.")
FieldName = Annotated[str, Field(pattern=FIELD_NAME_PATTERN, description="Field name.")]

MAX_D = 8
MAX_DIM = 8  # triangulation dimension (k+1)(d-k)


class _Strict(BaseModel):
    # strict: a number given as a string, or a boolean for a number, is a 422
    model_config = ConfigDict(extra="forbid", strict=True)


class _OneForm(_Strict):
    """A flat or flats given in one of the alternative sets of arrays of ``_forms``
    (pairs, or one array for points)."""

    _forms: ClassVar[dict[str, tuple[str, ...]]]

    @model_validator(mode="after")
    def _one(self):
        """Exactly one of the alternative sets of arrays is given (as the schema says)."""
        given = [name for name, keys in self._forms.items()
                 if any(getattr(self, key) is not None for key in keys)]
        if len(given) > 1:
            raise ValueError(f"give one of {' / '.join(self._forms)}, not {' and '.join(given)}")
        if not given:
            raise ValueError(f"give one of {' / '.join(self._forms)} (no arrays given)")
        return self

    @classmethod
    def __get_pydantic_json_schema__(cls, core_schema, handler):
        """The schema says what the validator takes: one set of arrays, all given."""
        js = handler.resolve_ref_schema(handler(core_schema))
        js["anyOf"] = [{"required": list(keys),
                        "properties": {key: {"not": {"type": "null"}} for key in keys}}
                       for keys in cls._forms.values()]
        return js


class CenterFlat(_OneForm):
    """One flat: (Q, r), or (A, b) with A (d, k), or a line as origin + direction, or
    (k = 0) a point."""

    Q: Optional[Mat] = None
    r: Optional[Vec] = None
    A: Optional[Mat] = None
    b: Optional[Vec] = None
    origin: Optional[Vec] = None
    direction: Optional[Vec] = None
    point: Optional[Vec] = None

    _forms = {"Q+r": ("Q", "r"), "A+b": ("A", "b"), "origin+direction": ("origin", "direction"),
              "point": ("point",)}


class TangentSimplexBasis(_Strict):
    """Tangent-space base simplex around a centre flat (paper Sec. 5.1, Eq. 13-15)."""

    kind: Literal["tangent_simplex"] = "tangent_simplex"
    center: Optional[CenterFlat] = Field(
        None, description="Centre flat; default: the span of the last k axes through the origin "
                          "(the z-axis for lines in R^3)."
    )
    scale: float = Field(0.01, gt=0, le=1e3, allow_inf_nan=False)
    variant: Literal["tangent", "paper"] = "tangent"


class FlatsModel(_OneForm):
    """A batch of flats in one form: Q (n,d,d) + r (n,d), A (n,d,k) + b (n,d),
    (k = 1) origins + directions (n,d), or (k = 0) points (n,d) (the forms of
    :class:`flatserve.flats.Flats`)."""

    Q: Optional[RowMats] = None
    r: Optional[Rows] = None
    A: Optional[RowMats] = None
    b: Optional[Rows] = None
    origins: Optional[Rows] = None
    directions: Optional[Rows] = None
    points: Optional[Rows] = None

    _forms = {"Q+r": ("Q", "r"), "A+b": ("A", "b"), "origins+directions": ("origins", "directions"),
              "points": ("points",)}


class FlatsBasis(FlatsModel):
    """A basis given explicitly: m flats in one form."""

    kind: Literal["flats"] = "flats"


Scale = Annotated[float, Field(gt=0, le=1e3, allow_inf_nan=False)]


class _AtlasSpec(_Strict):
    """Several tangent-simplex charts that together hold the flats they claim
    (:class:`flatserve.atlas.Atlas`): samples are inserted into every chart whose
    domain holds them, queries blended over the charts that hold them."""

    kind: Literal["atlas"] = "atlas"
    oriented: Optional[bool] = Field(
        None, description="Deprecated: the field's top-level `oriented` (kept for requests "
                          "written before it; if both are given they must agree).")


def _radius(ge: float | None = None, *, description: str):
    """An optional radius in degrees below a chart's 45 (above 0, or at least ``ge``)."""
    bound = {"gt": 0} if ge is None else {"ge": ge}
    return Field(None, lt=45, allow_inf_nan=False, description=description, **bound)


class CoveringAtlas(_AtlasSpec):
    """Centres chosen so that every orientation lies well inside some chart
    (:meth:`flatserve.atlas.Atlas.covering`): the default of a field without `basis`."""

    atlas: Literal["covering"] = Field(
        "covering", description="`covering`: every orientation of k-flats lies well inside "
                                "some chart (Atlas.covering).")
    inner: Optional[float] = _radius(
        0, description="Degrees: a chart's blending weight is 1 for flats whose centre is "
                    "closer (with `relative`: closer than the nearest centre's angle plus "
                    "this). Default: 12 (R^2, R^3), 2 with `relative`.")
    trusted: Optional[float] = _radius(
        description="Degrees: a chart answers no query farther (its weight falls to 0 "
                    "from `inner` to here; with `relative`, beyond the nearest centre's "
                    "angle). Default: 24 (R^2, R^3), 6 with `relative`.")
    reach: Optional[float] = _radius(
        description="Degrees: samples are stored in every chart whose centre is closer (at "
                    "least the charts' `trusted`, below 45; with `relative`, closer than the "
                    "nearest centre's angle plus this). Default: 3 degrees beyond "
                    "`trusted` (lines in R^3: 27; with `relative`: 14). Wider keeps more "
                    "samples around a chart's border, which sparse samples need (eyes far apart: about the covering "
                    "radius plus their spacing), at the cost of storing each sample in more "
                    "charts (describe's `atlas.duplication`).")
    relative: Optional[bool] = Field(
        None, description="Measure the charts' radii (`reach` included) from each flat's "
                           "nearest centre: a chart holds its share of the orientations and "
                           "a seam around it, so a sample is stored about 2.4 times (lines, "
                           "hyperplanes in R^4) instead of 4.1 (radii 2, 6, 14 degrees beyond "
                           "the nearest centre), at about the same error; about 1 % of random "
                           "queries fall outside the samples' hulls (docs/costs.md). Default "
                           "(null): true in R^4 and beyond, false in R^2 and R^3.")
    dense_reach: Optional[float] = _radius(
        description="With `relative`: degrees beyond each flat's nearest centre from which "
                    "a chart thins its seam (`seam_spacing`) or, once it holds `dense_after` "
                    "own samples (those it is the nearest chart of), stores nothing more "
                    "(above `trusted`, at most `reach`). Default: planes in R^4 with none of "
                    "the radii given, 7 with a `seam_spacing` of 1 (59 charts: a sample "
                    "stored 2.4 times at 3,000 samples, 2.3 at 12,000, where the seam of 14 "
                    "stores it 3.8 times; docs/costs.md); otherwise none. Give `reach` (14, "
                    "the default) for the plain seam.")
    dense_after: Optional[int] = Field(
        None, ge=0, le=1_000_000_000,
        description="With `dense_reach`: the own samples from which a chart stores nothing "
                    "beyond `dense_reach` (0: from the start; null: never).")
    seam_spacing: Optional[float] = Field(
        None, gt=0, le=1e6, allow_inf_nan=False,
        description="With `dense_reach`: beyond it, a chart stores a sample only if none of "
                    "the samples before it that the chart holds lies within this distance "
                    "of it in the chart's coordinates (at scale 1): a net of the outer seam, "
                    "which keeps the samples' hull as wide for fewer copies (null: every "
                    "sample up to `reach`).")
    isometric: Optional[bool] = Field(
        None, description="Warp the charts' points so that each chart measures turns and "
                          "shifts everywhere as at its centre (flatserve.warp: lines, and "
                          "k-flats of any k >= 1 by normal coordinates). Default: true for "
                          "lines in R^3, false otherwise (in 6 dimensions warped charts "
                          "answer fewer queries from sparse samples: docs/costs.md). Not "
                          "for points.")


class SamplesAtlas(_AtlasSpec):
    """Charts placed where the given flats are (:meth:`flatserve.atlas.Atlas.for_samples`):
    a greedy cover of their orientations within `radius` degrees, each chart's centre
    through the point nearest to its flats and its scale by the paper's bisection. Only
    the flats' region of the space is charted: a later sample farther than `reach` from
    every centre is rejected with its reason."""

    atlas: Literal["samples"]
    samples: FlatsModel = Field(
        description="The flats the atlas is built for (no values: upload the samples "
                    "afterwards); at most `max_atlas_samples` (FLATSERVE_MAX_ATLAS_SAMPLES).")
    radius: float = Field(30.0, gt=0, le=40.0, allow_inf_nan=False,
                          description="Degrees: every given flat is this close to a centre.")
    fraction: float = Field(0.99, gt=0, le=1, allow_inf_nan=False,
                            description="Of each chart's flats inside its simplex (the "
                                        "bisection of the chart's scale).")


class CentersAtlas(_AtlasSpec):
    """Charts around the given centre flats (:meth:`flatserve.atlas.Atlas.from_centers`),
    refused unless every orientation is within `trusted` of a centre and every chart
    round-trips its whole domain at its scale."""

    atlas: Literal["centers"]
    centers: FlatsModel = Field(description="One flat per chart (rays for oriented fields).")
    scale: Union[Scale, list[Scale]] = Field(
        1.0, description="Tangent-simplex scale of every chart, or one per centre.")


def _atlas_kind(v):
    """``atlas`` if given, else ``covering``."""
    if isinstance(v, dict):
        return v.get("atlas", "covering")
    return getattr(v, "atlas", None)


#: An atlas spec, by its member ``atlas``.
AtlasBasis = Annotated[
    Union[Annotated[CoveringAtlas, Tag("covering")], Annotated[SamplesAtlas, Tag("samples")],
          Annotated[CentersAtlas, Tag("centers")]],
    Discriminator(_atlas_kind),
]
#: The atlas specs' classes (``isinstance``).
ATLAS_SPECS = (CoveringAtlas, SamplesAtlas, CentersAtlas)


_FLATS_KEYS = tuple(n for names in FORMS.values() for n in names)


def _basis_kind(v):
    """``kind`` if given, else inferred: explicit flats when arrays are given."""
    if isinstance(v, dict):
        kind = v.get("kind")
        if kind is None:
            kind = "flats" if any(key in v for key in _FLATS_KEYS) else "tangent_simplex"
        return kind
    return getattr(v, "kind", None)


#: One chart: a tangent simplex or explicit flats (the stateless math routes).
ChartBasisSpec = Annotated[
    Union[Annotated[TangentSimplexBasis, Tag("tangent_simplex")], Annotated[FlatsBasis, Tag("flats")]],
    Discriminator(_basis_kind),
]
#: A field's basis: one chart, or an atlas of charts.
BasisSpec = Annotated[
    Union[Annotated[TangentSimplexBasis, Tag("tangent_simplex")], Annotated[FlatsBasis, Tag("flats")],
          Annotated[AtlasBasis, Tag("atlas")]],
    Discriminator(_basis_kind),
]


class _KD(_Strict):
    k: int = Field(1, ge=0, le=MAX_D - 1, description="Dimension of the flats (1: lines).")
    d: int = Field(3, ge=1, le=MAX_D, description="Dimension of the ambient space.")

    @model_validator(mode="after")
    def _kd(self):
        if self.k >= self.d:
            raise ValueError(f"k must be smaller than d (k={self.k}, d={self.d})")
        dim = basis_size(self.k, self.d) - 1
        if dim > MAX_DIM:
            raise ValueError(
                f"(k+1)(d-k) = {dim} exceeds {MAX_DIM}: "
                "triangulations of that dimension are not supported"
            )
        return self


def _example(example: dict) -> ConfigDict:
    """The request example of a body model, shown in the OpenAPI document (``/docs``);
    the examples of the request models are valid requests that follow one another
    (create ``demo``, upload to it, query it; tests/service/http/test_docs.py)."""
    return ConfigDict(json_schema_extra={"examples": [example]})


#: Two rays of the examples: eyes behind the screen z = 0, looking through it
_EXAMPLE_RAYS = {"origins": [[0.1, 0.2, -3.0], [-0.2, 0.1, -3.0]],
                 "directions": [[0.0, 0.0, 1.0], [0.05, -0.02, 1.0]]}


#: Most cameras of a field's ``rig``.
MAX_RIG_EYES = 4096
#: A finite JSON number (NaN and infinities refused).
_Finite = Annotated[float, Field(allow_inf_nan=False)]
_Point3 = Annotated[list[_Finite], Field(min_length=3, max_length=3)]


class RigSpec(_Strict):
    """The cameras of a capture whose field holds the depth channel
    (:class:`flatserve.lightfield.rig.DepthRig`): renders of the field go through
    it (:func:`flatserve.lightfield.depth.render_guided`)."""

    eyes: Annotated[list[_Point3], Field(min_length=2, max_length=MAX_RIG_EYES)] = Field(
        description=f"The capture's cameras' centres, (m, 3), 2 to {MAX_RIG_EYES} of them.")
    center: _Point3 = Field(description="The point the depth channel is measured from (the "
                                        "rig's centre): a sample's last value is its "
                                        "surface point's position along its line, from the "
                                        "line's point nearest this one.")


class FieldCreate(_KD):
    model_config = _example({"name": "demo", "channels": 1})
    name: FieldName
    channels: int = Field(1, ge=1, le=64, description="Values per sample (3 for RGB).")
    oriented: Optional[bool] = Field(
        None, description="Lines only (k = 1): a ray and its reverse are different samples "
                          "(charts over oriented lines); uploads and queries must then be rays "
                          "(origins + directions). Default false. Atlas fields only.")
    basis: Optional[BasisSpec] = Field(
        None, description="Default: a covering atlas (`{\"kind\": \"atlas\"}`: every "
                          "orientation accepted). `{\"kind\": \"tangent_simplex\"}` or "
                          "explicit flats: one chart (the paper's set-up).")
    roundtrip_tol: Optional[float] = Field(
        None, ge=1e-15, le=1.0, allow_inf_nan=False,
        description="Largest residual of a flat's coordinates' round trip for it to be "
                    "accepted (default 1e-6; at least 1e-15: the residuals of rounding "
                    "alone are about 1e-14).")
    unit: Union[Annotated[float, Field(ge=1e-6, le=1e6, allow_inf_nan=False)],
                Literal["data", "fit"], None] = Field(
        None,
        description="Atlas fields: the unit of length of the charts, in the flats' units "
                    "(1e-6 to 1e6): the "
                    "shift of a flat that counts as much as a turn of one radian (at a chart's "
                    "centre shifts and turns are then weighed alike). For rays of an object: "
                    "about its half-size (rays meeting on its surface at depth z from its "
                    "centre differ by a shift of z times their turn). `\"fit\"` (the default "
                    "up to R^4, a chart of at most 6 dimensions, but for points): chosen "
                    "from the field's first batch of samples and stored with it, by "
                    "held-out validation on its values among multiples of the geometry's "
                    "unit (1/4 to 8, and beyond an end; of the units within 5 % of the "
                    "least error, the one "
                    "nearest the geometry's): flatserve.atlas_field.fitted_unit. For a "
                    "smooth function that changes faster along a turn than along a shift, "
                    "0.34-0.53x the error of the geometry's unit up to R^3 and for "
                    "hyperplanes in R^4 (docs/costs.md); on the light-field scenes it is "
                    "the geometry's. It costs the first upload about a second up to R^3, "
                    "20-30 s for lines and planes in R^4 (other uploads to the field wait); "
                    f"a first batch of fewer than {FIT_MIN_ROWS} rows takes the geometry's. "
                    "`\"data\"` (the default beyond R^4): the geometry's unit, at no cost "
                    "(the mean distance of the first batch's flats from their least-squares "
                    "centre, samples of a background value left out: "
                    "flatserve.atlas.data_unit). Describe gives the unit chosen.")

    @field_validator("unit", mode="wrap")
    @classmethod
    def _one_unit_error(cls, value, handler):
        # one error at `unit`, not one per member of the union
        try:
            return handler(value)
        except ValidationError:
            raise ValueError(f"expected a length from 1e-6 to 1e6, \"data\" or \"fit\", got "
                             f"{value!r}") from None
    copies: int = Field(
        1, ge=1, le=3,
        description="Cluster mode (`serve --ray`): copies of each shard, each on a different "
                    "node, so that a node's loss costs no reads (a server holding its fields "
                    "itself keeps one).")
    tiles: Union[Annotated[int, Field(ge=1, le=64)], Literal["auto"]] = Field(
        1,
        description="One-chart fields: split the chart's triangulation into this many tiles "
                    "(Tile & Merge), built on the server's cores at once, with the same answers "
                    "bit for bit. Default 1. \"auto\": one tile per core once the chart holds "
                    "enough samples to gain from it (flatserve.tiles.auto_tiles: from 20,000 "
                    "samples). Only for one chart: with an atlas basis (the default) "
                    "anything but 1, \"auto\" included, is refused (422), since an atlas "
                    "field's charts are its shards and already use the cores.")
    rig: Optional[RigSpec] = Field(
        None,
        description="A light field of a capture with depth (as `flatserve lightfield import` "
                    "creates on a sparse rig all around an object): the capture's cameras. "
                    "Only for oriented lines in R^3 (k = 1, d = 3, `oriented: true`) with at "
                    "least 2 channels, the last being the depth channel "
                    "(flatserve.lightfield.depth.depth_values); the others are the colours. "
                    "A render of the field then goes through the depth "
                    "(flatserve.lightfield.depth.render_guided) and has the colour channels "
                    "only. Null or left out: a plain field.")


class QueryBody(FlatsModel):
    """JSON query (small batches): one flat form."""

    model_config = _example(_EXAMPLE_RAYS)

    form: Optional[Form] = None


class UploadBody(QueryBody):
    """JSON upload (small batches): one flat form plus values (n, C)."""

    model_config = _example({**_EXAMPLE_RAYS, "values": [[0.5], [0.25]]})

    values: Rows


class CoordinatesRequest(_KD):
    model_config = _example({"basis": {"kind": "tangent_simplex", "scale": 0.01},
                             "flats": _EXAMPLE_RAYS})
    basis: Optional[ChartBasisSpec] = None
    flats: FlatsModel
    embed: bool = Field(False, description="Also return the embedded coordinates (n, m-1).")


class ProjectRequest(_KD):
    model_config = _example({"flats": _EXAMPLE_RAYS, "weights": [[0.5, 0.5], [1.5, -0.5]]})
    flats: FlatsModel = Field(description="The m flats combined.")
    weights: Mat = Field(description="(n, m) affine weights, each row summing to 1.")


