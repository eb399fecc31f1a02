"""Pydantic models of the service's answers: what a field, an upload, a snapshot, a
query's JSON answer, the limits and the health checks report.

The documents a client sends (field definitions, request bodies) are in
:mod:`.schemas`; these are the responses (FastAPI's ``response_model``), and the
rooms build them (:mod:`flatserve.service.rooms`).
"""
from __future__ import annotations

from typing import Literal, Optional, Union

from pydantic import BaseModel, Field

from ..coordinates import REASONS
from .rooms.catalogue import FieldState
from .schemas import Mat, Mats, RigSpec, Vec


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


class QueryResponse(BaseModel):
    values: list[list[Optional[float]]] = Field(description="(q, C); null outside (outside=nan).")
    inside: list[bool]
    status: list[int] = Field(description="Status per row: " + "; ".join(
        f"{int(code)} {text}" for code, text in REASONS.items()) + ".")
    ids: Optional[list[list[int]]] = Field(None, description="(q, D+1) sample ids, -1 for none.")
    weights: Optional[list[list[Optional[float]]]] = Field(None, description="(q, D+1) barycentric.")


class CoordinatesResult(BaseModel):
    weights: list[list[Optional[float]]]
    status: list[int]
    residual: list[Optional[float]]
    embedded: Optional[list[list[Optional[float]]]] = None


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
