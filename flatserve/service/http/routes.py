"""HTTP routes under ``/v1`` (plus health and metrics at the root).

CPU-heavy handlers are plain ``def`` (FastAPI runs them in the thread pool of
``workers`` threads; the native core releases the GIL); the body is read by an
``async`` dependency first.
"""
from __future__ import annotations

import os
import time
from typing import Annotated, Optional

import anyio.to_thread
from fastapi import APIRouter, Header, Query, Request, Response

from ...options import Form
from . import codec
from ..rooms import specs
from ..rooms.catalogue import FieldState
from .deps import (AnyField, BodyDep, CatalogueDep, FieldNamePath, FieldsDep, FollowerDep,
                   NoBody, OnceIdempotencyKey, QueriesDep, ReadAccess, ReadyField, SettingsDep,
                   SnapshotsDep, TransferDep, UploadsDep, WriteAccess, authorize, json_body,
                   json_body_doc, presented_key, request_example)
from .errors import (BODY_RESPONSES, COMMON_RESPONSES, FIELD_RESPONSES, FIELD_WRITE_RESPONSES,
                     GUARD_RESPONSES, UPLOAD_RESPONSES, WRITE_RESPONSES, ApiError)
from ..logs import note
from .query import QueryParams, answer, server_timing
from .responses import model_body
from ..schemas import (MIN_POSITION_DESCRIPTION, CoordinatesRequest, FieldCreate, ProjectRequest,
                       QueryBody, UploadBody)
from ..reports import (BatchList, CoordinatesResult, FieldInfo, FieldList, Health, ImportResult,
                       Limits, ProjectResult, QueryResponse, SnapshotResult, UploadResult)

#: header carrying the log position of a write (uploads carry it in the body too)
POSITION_HEADER = "Flatserve-Position"
MinPositionQuery = Annotated[Optional[int], Query(ge=0, description=MIN_POSITION_DESCRIPTION)]

VerboseQuery = Annotated[bool, Query(
    description="Also the basis flats (`basis.Q`, `basis.r`) and, for an atlas, every chart "
                "(`charts`: centre, scale, samples): several KB. Default: a summary "
                "(`ncharts`, `atlas`).")]

FormQuery = Annotated[Optional[Form], Query(
    description="Flat form of the body. JSON/.npz: inferred from the array names. "
                "`.npy`: required unless the field holds lines (k = 1; default `rays`) or "
                "points (k = 0; default `points`).")]

_BINARY = {"schema": {"type": "string", "format": "binary"}}
_LAYOUT = (
    "Bodies: `application/json` (small batches; arrays as nested lists), "
    "`application/x-npy` (ONE array of a real number type, read as float64, of shape (n, W), "
    "n >= 1: per row the flat - "
    "rays: origin(d) | direction(d); parametric: A(d x k, row-major) | b(d); flats: "
    "Q(d x d, row-major) | r(d); points (k = 0): point(d) - then, for uploads, the C values), "
    "or `application/x-npz` (named arrays origins+directions | A+b | Q+r | points, and "
    "values). Every batch has at least one row."
)


def _body_doc(model) -> dict:
    schema = model.model_json_schema()
    schema.pop("title", None)
    return {"requestBody": {"required": True, "content": {
        "application/json": {"schema": schema, **request_example(model)},
        codec.NPY: _BINARY,
        codec.NPZ: _BINARY,
    }}}


api = APIRouter(prefix="/v1")
health = APIRouter()


# -- fields -------------------------------------------------------------------
@api.post("/fields", status_code=201, response_model=FieldInfo, response_model_exclude_unset=True, tags=["fields"],
          dependencies=[WriteAccess], responses=WRITE_RESPONSES,
          openapi_extra=json_body_doc(FieldCreate),
          summary="Create a field (basis + empty triangulation)",
          description="Without `basis`: a covering atlas (every orientation accepted; "
                      "`oriented: true` for rays). `basis` chooses one chart "
                      "(`tangent_simplex`, explicit flats) or another atlas (`samples`: "
                      "charts where given flats are; `centers`: explicit centres, checked to "
                      "cover every orientation).")
def create_field(spec: json_body(FieldCreate), fields: FieldsDep, follower: FollowerDep,
                 settings: SettingsDep, response: Response,
                 verbose: VerboseQuery = False) -> FieldInfo:
    note(field=spec.name)
    stored, basis = specs.field_spec(spec, max_atlas_samples=settings.max_atlas_samples)
    e = fields.create(spec.name, stored, basis)
    response.headers[POSITION_HEADER] = str(follower.applied)
    return fields.describe(e, verbose)


@api.get("/fields", response_model=FieldList, response_model_exclude_unset=True, tags=["fields"], dependencies=[ReadAccess, NoBody],
         responses=COMMON_RESPONSES, summary="List fields")
def list_fields(fields: FieldsDep) -> FieldList:
    return FieldList(fields=fields.summaries())


@api.get("/fields/{name}", response_model=FieldInfo, response_model_exclude_unset=True, tags=["fields"], dependencies=[ReadAccess, NoBody],
         responses=FIELD_RESPONSES, summary="Describe a field")
async def describe_field(name: FieldNamePath, fields: FieldsDep, queries: QueriesDep,
                         catalogue: CatalogueDep,
                         min_position: MinPositionQuery = None,
                         verbose: VerboseQuery = False) -> FieldInfo:
    await queries.wait_position(min_position)
    e = catalogue.get(name, need_ready=False)
    return await anyio.to_thread.run_sync(fields.describe, e, verbose)


@api.delete("/fields/{name}", status_code=204, tags=["fields"], dependencies=[WriteAccess, NoBody],
            responses=FIELD_WRITE_RESPONSES, summary="Delete a field and its stored batches")
def delete_field(name: FieldNamePath, fields: FieldsDep) -> Response:
    pos = fields.delete(name)
    return Response(status_code=204, headers={POSITION_HEADER: str(pos)})


@api.get("/fields/{name}/batches", response_model=BatchList, response_model_exclude_unset=True, tags=["fields"],
         dependencies=[ReadAccess, NoBody], responses=FIELD_RESPONSES, summary="List stored batches")
def list_batches(e: AnyField, uploads: UploadsDep) -> BatchList:
    return BatchList(batches=uploads.batches(e))


@api.post("/fields/{name}/snapshot", response_model=SnapshotResult, response_model_exclude_unset=True, tags=["fields"],
          dependencies=[WriteAccess, NoBody], responses=FIELD_WRITE_RESPONSES,
          summary="Write a snapshot now")
def snapshot_field(e: ReadyField, snapshots: SnapshotsDep) -> SnapshotResult:
    return snapshots.snapshot(e)


@api.get("/fields/{name}/export", tags=["fields"], dependencies=[ReadAccess],
         response_class=Response, responses={
             **FIELD_RESPONSES, 200: {"content": {codec.NPZ: _BINARY}, "description":
                                      "The field as one `.npz`: its definition and every "
                                      "stored batch (`flatserve/service/rooms/transfer.py`)."}},
         summary="Export a field as one file (for POST /v1/fields/{name}/import)")
def export_field(e: ReadyField, transfer: TransferDep) -> Response:
    body = transfer.export(e)
    return Response(body, media_type=codec.NPZ, headers={
        "Content-Disposition": f'attachment; filename="{e.name}.flatserve.npz"'})


@api.post("/fields/{name}/import", response_model=ImportResult, tags=["fields"],
          dependencies=[WriteAccess], responses=UPLOAD_RESPONSES,
          openapi_extra={"requestBody": {"required": True, "content": {codec.NPZ: _BINARY}}},
          summary="Create a field from an export file (of this or another deployment)",
          description="The field `name` is created with the file's definition (as exported: "
                      "an atlas is not built again) and the file's batches are stored in their "
                      "order, each under the Idempotency-Key `import-<export id>.<seq>`: the "
                      "field then answers bit for bit as the exported one. Repeating an import "
                      "that failed half-way stores only the missing batches (an existing field "
                      "of the file's definition is taken; another is a 409). The body is the "
                      "file as `application/x-npz` (up to `max_body_bytes`).")
def import_field(name: FieldNamePath, transfer: TransferDep, body: BodyDep, response: Response,
                 content_type: Annotated[Optional[str], Header()] = None) -> ImportResult:
    if codec.media_type(content_type) != codec.NPZ:
        raise ApiError(415, f"an import body is the export file as {codec.NPZ}, not "
                            f"{codec.media_type(content_type) or 'no Content-Type'}")
    codec.check_body(body, "npz")
    note(field=name)
    out = transfer.import_field(name, body)
    response.headers[POSITION_HEADER] = str(out.position)
    return out


# -- samples and queries --------------------------------------------------------
@api.post(
    "/fields/{name}/samples", response_model=UploadResult, response_model_exclude_unset=True, tags=["samples"],
    dependencies=[WriteAccess, OnceIdempotencyKey], responses=UPLOAD_RESPONSES,
    openapi_extra=_body_doc(UploadBody),
    summary="Upload a batch of samples",
    description="Stores the batch durably (acknowledged only after its commit to the "
                "shared log; the response's `position` is its log position, for reads with "
                "`min_position` on any replica). "
                "`wait=true` (default): acknowledged once the batch is also inserted into the "
                "triangulation (visible to queries). `wait=false`: acknowledged as soon as the "
                "batch's coordinates are computed (accepted/rejected rows and reasons are "
                "exact) and it is committed; it is then inserted in the background in commit "
                "order, in slices of `insert_slice_rows` samples that queries see as they go "
                "in (a field in tiles: the batch whole) (`indexed: false` in the response; the field's `indexed_batch` / "
                "`pending_samples` tell when it is wholly visible; a later "
                "`wait=true` upload or a query with `wait=true` waits for it). "
                + _LAYOUT + " With `Idempotency-Key`, a retried batch is stored once; the same "
                "key with different content is a 422, the header sent twice a 400.",
)
def upload_samples(
    e: ReadyField, uploads: UploadsDep, settings: SettingsDep, body: BodyDep,
    response: Response, form: FormQuery = None,
    wait: Annotated[bool, Query(description="Acknowledge after indexing (true) or after "
                                            "the durable commit (false).")] = True,
    content_type: Annotated[Optional[str], Header()] = None,
    idempotency_key: Annotated[Optional[str], Header(max_length=256)] = None,
) -> UploadResult:
    t0 = time.perf_counter()
    flats, values, _ = codec.decode(body, content_type, form, k=e.spec.k, d=e.spec.d,
                                    field=e.name, channels=e.spec.channels,
                                    max_rows=settings.max_batch_rows,
                                    max_json_bytes=settings.max_json_bytes)
    timings = {"decode": time.perf_counter() - t0}
    # an empty Idempotency-Key header means "no key", not the key ""
    out = uploads.upload(e, flats, values, idempotency_key or None, timings, wait=wait)
    response.headers["Server-Timing"] = server_timing(timings)
    response.headers[POSITION_HEADER] = str(out.position)
    return out


@api.post(
    "/fields/{name}/query", response_model=QueryResponse, tags=["samples"],
    dependencies=[ReadAccess], openapi_extra=_body_doc(QueryBody),
    responses={**BODY_RESPONSES, 200: {"content": {codec.NPY: _BINARY, codec.NPZ: _BINARY},
                                       "description": "Interpolated values."}},
    summary="Interpolate values at a batch of flats",
    description=_LAYOUT + " Response per `Accept`: JSON (default), `application/x-npy` "
                "(q, C + 1 [+ 2 (D+1)] [+ 1]) float32 or float64: values, inside as 0/1, then "
                "with `weights=true` sample ids and barycentric weights, and with "
                "`status=true` last each row's status code (the codes of JSON's `status`, "
                "listed in its schema); or `application/x-npz`.",
)
async def query_field(
    name: FieldNamePath, queries: QueriesDep, body: BodyDep,
    params: Annotated[QueryParams, Query()],
    content_type: Annotated[Optional[str], Header()] = None,
    accept: Annotated[Optional[str], Header()] = None,
) -> Response:
    # Usually answered by flatserve.service.http.fastpath (the same answer() and parameter
    # model, without FastAPI's per-request costs); this route is the documented reference.
    return await answer(queries, name, params, body, content_type, accept)


@api.get("/limits", response_model=Limits, tags=["service"], dependencies=[ReadAccess],
         responses=COMMON_RESPONSES, summary="This server's request limits",
         description="What a client splits its batches by (`max_batch_rows`, `max_body_bytes`, "
                     "`max_json_bytes`): the server's settings of those names.")
def limits(settings: SettingsDep) -> Limits:
    return Limits(max_batch_rows=settings.max_batch_rows, max_body_bytes=settings.max_body_bytes,
                  max_json_bytes=settings.max_json_bytes,
                  max_pending_samples=settings.max_pending_samples)


# -- stateless math ---------------------------------------------------------------
@api.post("/math/coordinates", response_model=CoordinatesResult, tags=["math"],
          dependencies=[ReadAccess], responses=COMMON_RESPONSES,
          openapi_extra=json_body_doc(CoordinatesRequest),
          summary="Coordinates of flats in a basis (paper Eq. 9/12)")
def math_coordinates(req: json_body(CoordinatesRequest), settings: SettingsDep) -> Response:
    basis = specs.build_basis(req.basis, req.k, req.d)
    flats = specs.flats_of(req.flats, req.k, req.d, "flats", settings.max_batch_rows)
    m = basis.m  # weights (m), status, residual (+ embedded (m - 1))
    _check_math_answer(len(flats), m + 2 + (m - 1 if req.embed else 0), settings)
    c = basis.coordinates_of(flats)
    extra = {}
    if req.embed:
        from ...embedding import embed
        extra["embedded"] = embed(c.weights)
    return model_body(CoordinatesResult, weights=c.weights, status=c.status,
                      residual=c.residual, **extra)


@api.post("/math/project", response_model=ProjectResult, tags=["math"],
          dependencies=[ReadAccess], responses=COMMON_RESPONSES,
          openapi_extra=json_body_doc(ProjectRequest),
          summary="Projection of an affine combination of flats (paper Eq. 4-6)")
def math_project(req: json_body(ProjectRequest), settings: SettingsDep) -> Response:
    from ... import flats
    from ..._validate import as_array

    Q, r = specs.flats_from(req.flats, req.k, req.d, "flats", settings.max_batch_rows,
                            validate=False)
    w = as_array(req.weights, "weights", ("n", Q.shape[0]))
    if w.shape[0] > settings.max_batch_rows:
        from ..status import BatchTooLargeError
        raise BatchTooLargeError(f"{w.shape[0]} weight rows; the limit is {settings.max_batch_rows}")
    d, k = req.d, req.k  # per row: Q (d x d), r (d), A (d x k), b (d), gap, ambiguous
    _check_math_answer(w.shape[0], d * d + 2 * d + d * k + 2, settings)
    p = flats.affine_combination(w, Q, r, req.k)
    A, b = flats.to_parametric(p.Q, p.r, req.k)
    return model_body(ProjectResult, Q=p.Q, r=p.r, A=A, b=b, gap=p.gap, ambiguous=p.ambiguous)


def _check_math_answer(rows: int, per_row: int, settings) -> None:
    """413 for a math answer over ``max_json_answer_bytes``, before it is computed (its
    work grows as its size: rows x d^2)."""
    codec.check_answer(rows, per_row, "json", max_json=settings.max_json_answer_bytes,
                       max_binary=settings.max_answer_bytes,
                       bulk="compute large batches in-process with the library "
                            "(flatserve.Basis.coordinates_of, flatserve.flats."
                            "affine_combination)")


# -- health and metrics -------------------------------------------------------------
@health.get("/healthz", response_model=Health, response_model_exclude_unset=True, tags=["health"],
            dependencies=[NoBody], responses=GUARD_RESPONSES, summary="Liveness")
def healthz() -> Health:
    return Health(status="ok")


@health.get("/readyz", response_model=Health, tags=["health"], summary="Readiness",
            description="200 once the stored fields are restored and the replica follows "
                        "the log; 503 while they load or the database is unreachable. A "
                        "field that failed (its restore, or a log entry it cannot apply) "
                        "does not make the replica unready (every replica would fail it "
                        "alike): it is listed in `failed_fields` (its requests get 503 "
                        "naming the error). Without a key (when keys are on) the answer is "
                        "the status alone; the details (fields loading and failed, the log "
                        "position, the pid, the backend, the storage error) need the read "
                        "key.",
            dependencies=[NoBody],
            responses={**GUARD_RESPONSES,
                       503: {"model": Health, "description": "Stored fields still loading."}})
def readyz(request: Request, catalogue: CatalogueDep, follower: FollowerDep,
           settings: SettingsDep) -> Response:
    try:
        authorize(settings, presented_key(request.scope["headers"]), write=False)
        details = True
    except ApiError:  # a missing or wrong key: the status only
        details = False
    states = catalogue.counts()
    loading, failed = states[FieldState.LOADING], states[FieldState.FAILED]
    body = {"fields": sum(map(len, states.values())), "loading": len(loading),
            "loading_fields": loading, "failed": len(failed), "failed_fields": failed,
            "pid": os.getpid(), "backend": follower.backend_kind}
    try:
        body.update(follower.progress())
    except Exception as exc:  # the database is unreachable: not ready
        body["error"] = str(exc)
        status, code = "storage unavailable", 503
    else:
        status, code = ("ready", 200) if catalogue.ready.is_set() else ("loading", 503)
    return model_body(Health, code, status=status, **(body if details else {}))


@health.get("/metrics", tags=["health"], summary="Prometheus metrics",
            response_class=Response, dependencies=[ReadAccess, NoBody],
            responses={**COMMON_RESPONSES, 200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                             "description": "Prometheus text format."}})
def metrics(request: Request) -> Response:
    from .metrics import CONTENT_TYPE

    return Response(request.app.state.metrics.render(), media_type=CONTENT_TYPE)
