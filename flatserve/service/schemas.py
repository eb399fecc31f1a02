"""Pydantic models of the small JSON documents (field definitions, reports).

Bulk arrays (upload and query bodies) are NOT parsed through these models: the
``*Body`` models below only document the JSON form in OpenAPI; the service
decodes them with orjson + NumPy (see :mod:`.codec`).
"""
from __future__ import annotations

from typing import Annotated, ClassVar, Literal, Optional, Union

from pydantic import (BaseModel, ConfigDict, Discriminator, Field, Tag, ValidationError,
                      field_validator, model_validator)

from ..atlas_field import FIT_MIN_ROWS
from ..coordinates import REASONS
from ..flats import FORMS, basis_size
from ..options import Form
from .rooms.catalogue import FieldState
from .settings import FIELD_NAME_PATTERN

Vec = list[float]
Mat = list[list[float]]
Mats = list[list[list[float]]]
#: A batch's per-row array, (n, W) or (n, a, b): every batch has at least one row.
#: Said in the schema only (``minItems``); the service's decoder (:mod:`.codec`,
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
    (create ``demo``, upload to it, query it; tests/service/test_docs.py)."""
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


class BasisInfo(BaseModel):
    m: int
    dim: int = Field(description="(k+1)(d-k): dimension of the coordinate space.")
    spec: dict
    Q: Optional[Mats] = Field(None, description="The basis flats (m, d, d); of an atlas field, "
                                                "chart 0's as created, in the unit given then "
                                                "(`verbose=true` only).")
    r: Optional[Mat] = Field(None, description="(m, d) (`verbose=true` only).")


class ChartCenter(BaseModel):
    A: Mat = Field(description="(d, k) orthonormal directions of the centre flat (oriented "
                               "atlases: the chart's ray direction).")
    r: Vec = Field(description="(d,) the centre flat's point closest to the origin.")


class ChartInfo(BaseModel):
    center: ChartCenter
    scale: float = Field(description="Tangent-simplex scale of the chart.")
    samples: Optional[int] = Field(description="Samples (vertices) in the chart's "
                                               "triangulation; null while loading.")


class AtlasInfo(BaseModel):
    method: Optional[str] = Field(None, description="How the charts were placed: `covering`, "
                                                    "`samples` or `centers`.")
    oriented: bool = Field(description="The field's `oriented`.")
    inner: float = Field(description="Degrees from a centre up to which its blending weight is 1.")
    trusted: float = Field(description="Degrees from a centre beyond which the chart answers no "
                                       "query (its blending weight is 0).")
    reach: float = Field(description="Degrees: samples are inserted into every chart whose "
                                     "centre is closer.")
    unit: Optional[float] = Field(
        1.0, description="The charts' unit of length (the field's `unit`); null while it is "
                         "to be chosen from the first batch of samples.")
    unit_from: str = Field("given", description="`given` (the create request's `unit`, or 1 "
                                                "for fields stored before the choice from the "
                                                "data), `data` (chosen from the first batch's "
                                                "flats) or `fit` (from its values).")
    relative: bool = Field(False, description="The radii are degrees beyond each flat's "
                                              "nearest centre (the create request's "
                                              "`basis.relative`, by default true in R^4 "
                                              "and beyond).")
    dense_reach: Optional[float] = Field(
        None, description="Degrees beyond each flat's nearest centre from which a chart thins "
                          "its seam (`seam_spacing`) or, once dense (`dense_after`), stores "
                          "nothing more (null: every sample up to `reach`; by default planes "
                          "in R^4: 7).")
    dense_after: Optional[int] = Field(
        None, description="Own samples (those it is the nearest chart of) from which a chart "
                          "stores nothing beyond `dense_reach` (null: never).")
    seam_spacing: Optional[float] = Field(
        None, description="Beyond `dense_reach` a chart stores a sample only if none it holds "
                          "lies within this distance in its coordinates (null: no net; by "
                          "default planes in R^4: 1).")
    isometric: bool = Field(False, description="The charts' points are warped to measure turns "
                                               "and shifts everywhere as at their centres "
                                               "(by default lines in R^3, created since this "
                                               "existed; any kind asked for; flatserve.warp).")
    covering_radius: Optional[float] = Field(
        None, description="Degrees: every orientation measured was this close to a centre "
                          "(`covering` and `centers`; null for `samples`, which charts only "
                          "the region of its flats).")
    max_sample_angle: Optional[float] = Field(
        None, description="`samples`: degrees from the farthest given flat to its nearest "
                          "centre.")
    nstored: Optional[int] = Field(description="Vertices over all charts (a sample in each "
                                               "chart holding it); null while loading.")
    duplication: Optional[float] = Field(
        None, description="nstored / nsamples; null while empty.")


class StorageInfo(BaseModel):
    batches: int
    batch_rows: int
    batch_bytes: int
    last_batch: int
    snapshot_batch: int = Field(description="Last batch included in the snapshot (0: none).")
    snapshot_bytes: int
    total_bytes: int


class FieldSummary(BaseModel):
    name: str
    k: int
    d: int
    channels: int
    state: FieldState
    nsamples: Optional[int] = None
    oriented: bool = Field(False, description="Rays keep their direction (uploads and "
                                              "queries must be rays).")


class FieldList(BaseModel):
    fields: list[FieldSummary]


class TileInfo(BaseModel):
    node: str = Field(description="The Ray node the tile's actor runs on.")
    pid: int = Field(description="The process id of the tile's actor on that node.")
    memory: int = Field(description="Resident bytes of the tile's process.")
    npoints: int = Field(description="Points the tile holds: its own and its halo.")


class ShardGroupInfo(BaseModel):
    charts: list[int] = Field(description="The charts this group of shards holds.")
    copies: int = Field(description="Copies of the group the field asks for (each in an "
                                    "actor on its own node, placed as far as the live nodes "
                                    "with room hold them).")
    live: int = Field(description="Copies heard from and ready at the last status round (each "
                                  "second, and at each describe); 0 before any has reported.")
    unplaced: Optional[str] = Field(None, description="With no live copy: why none can be "
                                    "placed now (no live node has room for a shard) and what "
                                    "would fix it; null otherwise.")
    position: Optional[int] = Field(None, description="Log position the most advanced copy "
                                                      "has applied.")
    samples: Optional[int] = Field(None, description="Distinct samples of its charts.")
    memory: Optional[int] = Field(None, description="Resident bytes of that copy's process.")
    node: Optional[str] = Field(None, description="The Ray node that copy runs on.")
    restored_from: Optional[str] = Field(None, description="What that copy restored itself "
                                                           "from: a snapshot, or the log.")
    tiles: Optional[list[TileInfo]] = Field(None, description="A one-chart field in tiles: "
                                            "that copy's tiles, each in a Ray actor of its own.")


class FieldInfo(FieldSummary):
    ndim: int
    position: int = Field(0, description="The log position this replica has applied (a "
                                         "read-your-writes token for `min_position`).")
    indexed_batch: int = Field(0, description="Last batch inserted into the triangulation "
                                              "(batches up to it are visible to queries).")
    pending_batches: int = Field(0, description="Acknowledged (stored) batches not yet "
                                                "indexed (uploads with wait=false).")
    pending_samples: int = Field(0, description="Accepted samples of the pending batches.")
    nrejected: Optional[int] = None
    nvertices: Optional[int] = Field(None, description="Vertices of the triangulation (atlas "
                                                       "fields: over all charts).")
    nsimplex: Optional[int] = Field(None, description="Cells of the triangulation (atlas "
                                                      "fields: over all charts).")
    created: float
    error: Optional[str] = None
    basis: BasisInfo
    storage: StorageInfo
    atlas: Optional[AtlasInfo] = Field(None, description="Atlas fields: the atlas's radii and "
                                                         "sizes (null: one chart).")
    ncharts: int = Field(1, description="Charts of the field (1: one chart).")
    tiles: Union[int, Literal["auto"]] = Field(
        1, description="Tiles of a one-chart field's triangulation, as created (1: one).")
    ntiles: Optional[int] = Field(
        None, description="Tiles of a one-chart field now (\"auto\": as many as its size gave "
                          "so far); null for an atlas field, while the field loads, or when "
                          "its shards live elsewhere (cluster mode).")
    shard_groups: Optional[list[ShardGroupInfo]] = Field(
        None, description="Cluster mode (`serve --ray`): where the field's shards live, per "
                          "group of charts (absent when this server holds the field itself).")
    charts: Optional[list[ChartInfo]] = Field(
        None, description="Atlas fields with `verbose=true`: per chart its centre, scale and "
                          "samples (absent by default, and for one chart, described by `basis`).")
    rig: Optional[RigSpec] = Field(
        None, description="The create request's `rig` (absent for a field without one): its "
                          "renders go through its last channel, the depth channel.")


class UploadResult(BaseModel):
    batch: int = Field(description="Sequence number of the stored batch.")
    accepted: int
    rejected: list[int] = Field(description="Row indices not triangulated (outside the chart; "
                                            "atlas fields: outside every chart's domain).")
    reasons: list[str]
    duplicates: Optional[int] = Field(
        description="Accepted rows that coincided with an existing sample; null until indexed "
                    "(wait=false).")
    nsamples: int = Field(description="Samples in the field after this batch (wait=true); with "
                                      "wait=false the samples indexed when it was acknowledged.")
    indexed: bool = Field(True, description="The batch is in the triangulation (visible to "
                                            "queries). wait=false: false when acknowledged; see "
                                            "`indexed_batch` of the field.")
    pending_samples: int = Field(0, description="Accepted samples stored but not yet indexed "
                                                "when acknowledged (this batch included).")
    replayed: bool = Field(False, description="True: the Idempotency-Key was seen; nothing stored.")
    position: int = Field(0, description="The batch's position in the shared log: pass it as "
                                         "`min_position` to a query or describe on any replica "
                                         "to read this write.")


class ImportResult(BaseModel):
    name: str = Field(description="The field created (or completed) from the file.")
    source: str = Field(description="The name of the field the file was exported from.")
    batches: int = Field(description="Batches in the file, stored in their order.")
    replayed_batches: int = Field(description="Of them, stored already by an earlier import "
                                              "of the same file (nothing stored twice).")
    accepted: int = Field(description="Samples accepted by the batches stored now.")
    nsamples: int = Field(description="Samples in the field after the import.")
    position: int = Field(description="Log position of the last batch (`min_position` for "
                                      "reads on other replicas).")


class BatchInfo(BaseModel):
    batch: int
    idempotency_key: Optional[str]
    rows: int
    accepted: Optional[int] = Field(
        description="Accepted rows; null while the batch's response is not stored yet "
                    "(an upload in flight, or a response lost in a crash: a retry with the "
                    "batch's Idempotency-Key recomputes it).")
    form: str


class BatchList(BaseModel):
    batches: list[BatchInfo]


class SnapshotResult(BaseModel):
    batch: int = Field(description="Last batch included in the snapshot.")
    bytes: int = Field(description="The snapshot's size: its file and the parts it names "
                                   "(an atlas field's charts).")
    written: int = Field(0, description="Bytes this snapshot wrote: its file and the parts of "
                                        "the charts that changed since the last one (0: the "
                                        "stored snapshot was up to date).")
    seconds: float


class QueryBody(FlatsModel):
    """JSON query (small batches): one flat form."""

    model_config = _example(_EXAMPLE_RAYS)

    form: Optional[Form] = None


class UploadBody(QueryBody):
    """JSON upload (small batches): one flat form plus values (n, C)."""

    model_config = _example({**_EXAMPLE_RAYS, "values": [[0.5], [0.25]]})

    values: Rows


class QueryResponse(BaseModel):
    values: list[list[Optional[float]]] = Field(description="(q, C); null outside (outside=nan).")
    inside: list[bool]
    status: list[int] = Field(description="Status per row: " + "; ".join(
        f"{int(code)} {text}" for code, text in REASONS.items()) + ".")
    ids: Optional[list[list[int]]] = Field(None, description="(q, D+1) sample ids, -1 for none.")
    weights: Optional[list[list[Optional[float]]]] = Field(None, description="(q, D+1) barycentric.")


class CoordinatesRequest(_KD):
    model_config = _example({"basis": {"kind": "tangent_simplex", "scale": 0.01},
                             "flats": _EXAMPLE_RAYS})
    basis: Optional[ChartBasisSpec] = None
    flats: FlatsModel
    embed: bool = Field(False, description="Also return the embedded coordinates (n, m-1).")


class CoordinatesResult(BaseModel):
    weights: list[list[Optional[float]]]
    status: list[int]
    residual: list[Optional[float]]
    embedded: Optional[list[list[Optional[float]]]] = None


class ProjectRequest(_KD):
    model_config = _example({"flats": _EXAMPLE_RAYS, "weights": [[0.5, 0.5], [1.5, -0.5]]})
    flats: FlatsModel = Field(description="The m flats combined.")
    weights: Mat = Field(description="(n, m) affine weights, each row summing to 1.")


class ProjectResult(BaseModel):
    Q: list[list[list[Optional[float]]]]
    r: list[list[Optional[float]]]
    A: list[list[list[Optional[float]]]]
    b: list[list[Optional[float]]]
    gap: list[Optional[float]]
    ambiguous: list[bool]


class Limits(BaseModel):
    """The request limits of this server (its settings), for clients that split
    their batches to fit (:class:`flatserve.client.Client` reads them once)."""

    max_batch_rows: int = Field(description="Most rows in one upload or query (413 past it).")
    max_body_bytes: int = Field(description="Largest request body (413).")
    max_json_bytes: int = Field(description="Largest JSON body (413).")
    max_pending_samples: int = Field(description="Accepted samples of one field waiting for "
                                                 "their insert before `wait=false` uploads get 429.")


class Health(BaseModel):
    status: str
    fields: Optional[int] = None
    loading: Optional[int] = None
    loading_fields: Optional[list[str]] = Field(
        None, description="Fields still being restored (the others answer already).")
    failed: Optional[int] = None
    failed_fields: Optional[list[str]] = Field(
        None, description="Fields that failed (their restore, or a log entry they cannot "
                          "apply): their requests get 503 naming the error; the replica "
                          "stays ready for the others.")
    pid: Optional[int] = Field(None, description="This replica's process id.")
    backend: Optional[str] = Field(None, description="Where the log is: sqlite or postgresql.")
    position: Optional[int] = Field(None, description="Log position this replica has applied "
                                                      "(null while restoring).")
    head: Optional[int] = Field(None, description="Position of the log's last committed entry.")
    lag_entries: Optional[int] = Field(None, description="head - position.")
    lag_seconds: Optional[float] = Field(
        None, description="Seconds since the oldest entry not yet applied here was committed "
                          "(0: caught up).")
    error: Optional[str] = None
