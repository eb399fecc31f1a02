"""HTTP routes under ``/v1`` (plus health and metrics at the root).

CPU-heavy handlers are plain ``def`` (FastAPI runs them in the thread pool of
``workers`` threads; the native core releases the GIL); the body is read by an
``async`` dependency first.
"""
from __future__ import annotations

import os
import time
from typing import Annotated, Literal, Optional

import anyio.to_thread
from fastapi import APIRouter, Header, Query, Request, Response

from ..atlas import Atlas
from .status import StorageError
from . import codec, specs, uploads
from .codec import JSONBytes
from .deps import (BodyDep, FieldNamePath, ReadAccess, RegistryDep, SettingsDep, WriteAccess,
                   json_body, json_body_doc)
from .entry import FieldEntry
from .errors import BODY_RESPONSES, COMMON_RESPONSES, FIELD_RESPONSES
from .query import Form, QueryParams, answer, server_timing, wait_position
from .schemas import (BatchList, CoordinatesRequest, CoordinatesResult, FieldCreate,
                      FieldInfo, FieldList, Health, ProjectRequest, ProjectResult,
                      QueryBody, QueryResponse, SnapshotResult, UploadBody, UploadResult)

#: header carrying the log position of a write (uploads carry it in the body too)
POSITION_HEADER = "Flatserve-Position"
MinPositionQuery = Annotated[Optional[int], Query(
    ge=0, description="Read-your-writes: answer only once this replica has applied the log "
                      "position a write returned (`position` of an upload, or the "
                      "`Flatserve-Position` header of any write), waiting up to "
                      "`read_wait_timeout` seconds; then 503 with `Retry-After` (any replica "
                      "answers it; one behind waits).")]

FormQuery = Annotated[Optional[Form], Query(
    description="Flat form of the body. JSON/.npz: inferred from the array names. "
                "`.npy`: required unless the field holds lines (k = 1; default `rays`).")]

_BINARY = {"schema": {"type": "string", "format": "binary"}}
_LAYOUT = (
    "Bodies: `application/json` (small batches; arrays as nested lists), "
    "`application/x-npy` (ONE array of a real number type, read as float64, of shape (n, W), "
    "n >= 1: per row the flat - "
    "rays: origin(d) | direction(d); parametric: A(d x k, row-major) | b(d); flats: "
    "Q(d x d, row-major) | r(d) - then, for uploads, the C values), or `application/x-npz` "
    "(named arrays origins+directions | A+b | Q+r, and values). Every batch has at least one row."
)


def _body_doc(model) -> dict:
    schema = model.model_json_schema()
    schema.pop("title", None)
    return {"requestBody": {"required": True, "content": {
        "application/json": {"schema": schema},
        codec.NPY: _BINARY,
        codec.NPZ: _BINARY,
    }}}


api = APIRouter(prefix="/v1")
health = APIRouter()


# -- fields -------------------------------------------------------------------
def _summary(e: FieldEntry) -> dict:
    f = e.field
    return {"name": e.name, "k": e.spec.k, "d": e.spec.d, "channels": e.spec.channels,
            "state": e.state, "oriented": e.spec.oriented,
            "nsamples": int(f.nsamples) if f is not None else None}


@api.post("/fields", status_code=201, response_model=FieldInfo, tags=["fields"],
          dependencies=[WriteAccess], responses=BODY_RESPONSES,
          openapi_extra=json_body_doc(FieldCreate),
          summary="Create a field (basis + empty triangulation)",
          description="Without `basis`: a covering atlas (every orientation accepted; "
                      "`oriented: true` for rays). `basis` chooses one chart "
                      "(`tangent_simplex`, explicit flats) or another atlas (`samples`: "
                      "charts where given flats are; `centers`: explicit centres, checked to "
                      "cover every orientation).")
def create_field(spec: json_body(FieldCreate), registry: RegistryDep,
                 settings: SettingsDep) -> Response:
    stored, basis = specs.field_spec(spec, max_atlas_samples=settings.max_atlas_samples)
    e = registry.create(spec.name, stored, basis)
    return JSONBytes(_describe(registry, e), status_code=201,
                     headers={POSITION_HEADER: str(registry.position)})


@api.get("/fields", response_model=FieldList, tags=["fields"], dependencies=[ReadAccess],
         responses=COMMON_RESPONSES, summary="List fields")
def list_fields(registry: RegistryDep) -> Response:
    return JSONBytes({"fields": [_summary(e) for e in registry.snapshot_entries()]})


def _describe(registry, e: FieldEntry) -> dict:
    if e.basis is None:  # a stored definition this version cannot read
        raise StorageError(f"field {e.name!r} could not be loaded: {e.error}")
    nb, nrows, nbytes, last = registry.storage.batch_stats(e.id)
    snap_bytes = registry.storage.snapshot_bytes(e.snapshot_file)
    out = _summary(e)
    f = e.field
    m = e.basis.m
    pending_batches, pending_samples = e.pending_counts()
    out.update({
        "ndim": m - 1,
        "position": registry.position,
        "indexed_batch": e.indexed_seq,
        "pending_batches": pending_batches,
        "pending_samples": pending_samples,
        "nrejected": int(f.nrejected) if f is not None else None,
        "nvertices": None if f is None else int(f.nstored if e.spec.is_atlas else f.nsamples),
        "nsimplex": int(f.nsimplex) if f is not None else None,
        "created": e.created,
        "error": e.error,
        "basis": {"m": m, "dim": m - 1, "spec": e.spec.basis, "Q": e.basis.Q, "r": e.basis.r},
        "storage": {"batches": nb, "batch_rows": nrows, "batch_bytes": nbytes, "last_batch": last,
                    "snapshot_batch": e.snapshot_seq if e.snapshot_file else 0,
                    "snapshot_bytes": snap_bytes, "total_bytes": nbytes + snap_bytes},
    })
    if e.spec.is_atlas:
        out.update(_describe_atlas(e))
    return out


def _describe_atlas(e: FieldEntry) -> dict:
    """``atlas`` and ``charts`` of an atlas field's description (sizes null while loading)."""
    spec = e.spec.atlas
    f = e.field
    d = f.describe() if f is not None else None
    per = [None] * len(spec["scales"]) if d is None else [c["samples"] for c in d["charts"]]
    info = spec.get("info", {})
    return {
        "atlas": {"method": info.get("method"), "oriented": spec["oriented"],
                  "inner": spec["inner"], "trusted": spec["trusted"], "reach": spec["reach"],
                  "unit": spec.get("unit", 1.0), "isometric": Atlas.spec_isometric(spec),
                  "covering_radius": info.get("covering_radius_deg"),
                  "max_sample_angle": info.get("max_sample_angle_deg"),
                  "nstored": None if d is None else d["nstored"],
                  "duplication": None if d is None else d["duplication"]},
        "charts": [{"center": {"A": A, "r": r}, "scale": s, "samples": n}
                   for A, r, s, n in zip(spec["center_A"], spec["center_r"], spec["scales"],
                                         per)],
    }


@api.get("/fields/{name}", response_model=FieldInfo, tags=["fields"], dependencies=[ReadAccess],
         responses=FIELD_RESPONSES, summary="Describe a field")
async def describe_field(name: FieldNamePath, registry: RegistryDep, settings: SettingsDep,
                         min_position: MinPositionQuery = None) -> Response:
    if min_position is not None:
        await wait_position(registry, settings, min_position)
    e = registry.get(name, need_ready=False)
    return JSONBytes(await anyio.to_thread.run_sync(_describe, registry, e))


@api.delete("/fields/{name}", status_code=204, tags=["fields"], dependencies=[WriteAccess],
            responses=FIELD_RESPONSES, summary="Delete a field and its stored batches")
def delete_field(name: FieldNamePath, registry: RegistryDep) -> Response:
    pos = registry.delete(name)
    return Response(status_code=204, headers={POSITION_HEADER: str(pos)})


@api.get("/fields/{name}/batches", response_model=BatchList, tags=["fields"],
         dependencies=[ReadAccess], responses=FIELD_RESPONSES, summary="List stored batches")
def list_batches(name: FieldNamePath, registry: RegistryDep) -> Response:
    e = registry.get(name, need_ready=False)
    return JSONBytes({"batches": uploads.batches(registry, e)})


@api.post("/fields/{name}/snapshot", response_model=SnapshotResult, tags=["fields"],
          dependencies=[WriteAccess], responses=FIELD_RESPONSES, summary="Write a snapshot now")
def snapshot_field(name: FieldNamePath, registry: RegistryDep) -> Response:
    return JSONBytes(registry.snapshot(registry.get(name)))


# -- samples and queries --------------------------------------------------------
@api.post(
    "/fields/{name}/samples", response_model=UploadResult, tags=["samples"],
    dependencies=[WriteAccess], responses=BODY_RESPONSES, openapi_extra=_body_doc(UploadBody),
    summary="Upload a batch of samples",
    description="Stores the batch durably (acknowledged only after its commit to the "
                "shared log; the response's `position` is its log position, for reads with "
                "`min_position` on any replica). "
                "`wait=true` (default): acknowledged once the batch is also inserted into the "
                "triangulation (visible to queries). `wait=false`: acknowledged as soon as the "
                "batch's coordinates are computed (accepted/rejected rows and reasons are "
                "exact) and it is committed; it is then inserted in the background in commit "
                "order, in slices of `insert_slice_rows` samples that queries see as they go "
                "in (`indexed: false` in the response; the field's `indexed_batch` / "
                "`pending_samples` tell when it is wholly visible; a later "
                "`wait=true` upload or a query with `wait=true` waits for it). "
                + _LAYOUT + " With `Idempotency-Key`, a retried batch is stored once; the same "
                "key with different content is a 422.",
)
def upload_samples(
    name: FieldNamePath, registry: RegistryDep, settings: SettingsDep, body: BodyDep,
    form: FormQuery = None,
    wait: Annotated[bool, Query(description="Acknowledge after indexing (true) or after "
                                            "the durable commit (false).")] = True,
    content_type: Annotated[Optional[str], Header()] = None,
    idempotency_key: Annotated[Optional[str], Header(max_length=256)] = None,
) -> Response:
    e = registry.get(name)
    t0 = time.perf_counter()
    flats, values, _ = codec.decode(body, content_type, form, k=e.spec.k, d=e.spec.d,
                                    channels=e.spec.channels, max_rows=settings.max_batch_rows,
                                    max_json_bytes=settings.max_json_bytes)
    timings = {"decode": time.perf_counter() - t0}
    # an empty Idempotency-Key header means "no key", not the key ""
    out = uploads.upload(registry, e, flats, values, idempotency_key or None, timings, wait=wait)
    return JSONBytes(out, headers={"Server-Timing": server_timing(timings),
                                   POSITION_HEADER: str(out["position"])})


@api.post(
    "/fields/{name}/query", response_model=QueryResponse, tags=["samples"],
    dependencies=[ReadAccess], openapi_extra=_body_doc(QueryBody),
    responses={**BODY_RESPONSES, 200: {"content": {codec.NPY: _BINARY, codec.NPZ: _BINARY},
                                       "description": "Interpolated values."}},
    summary="Interpolate values at a batch of flats",
    description=_LAYOUT + " Response per `Accept`: JSON (default), `application/x-npy` "
                "(q, C + 1 [+ 2 (D+1)]) float64: values, inside as 0/1, then with "
                "`weights=true` sample ids and barycentric weights; or `application/x-npz`.",
)
async def query_field(
    name: FieldNamePath, registry: RegistryDep, settings: SettingsDep, body: BodyDep,
    form: FormQuery = None,
    outside: Annotated[Literal["nan", "clamp"], Query()] = "nan",
    order: Annotated[Literal["hilbert", "given"], Query()] = "hilbert",
    weights: Annotated[bool, Query(description="Also return sample ids and weights.")] = False,
    wait: Annotated[bool, Query(description="First wait until every batch acknowledged "
                                            "so far, by any replica (also with wait=false), "
                                            "is indexed here.")] = False,
    min_position: MinPositionQuery = None,
    content_type: Annotated[Optional[str], Header()] = None,
    accept: Annotated[Optional[str], Header()] = None,
) -> Response:
    # Usually answered by flatserve.service.fastpath (the same answer(), without
    # FastAPI's per-request costs); this route is the documented reference.
    return await answer(registry, settings, name,
                        QueryParams(form, outside, order, weights, wait, min_position),
                        body, content_type, accept)


# -- stateless math ---------------------------------------------------------------
@api.post("/math/coordinates", response_model=CoordinatesResult, tags=["math"],
          dependencies=[ReadAccess], responses=COMMON_RESPONSES,
          openapi_extra=json_body_doc(CoordinatesRequest),
          summary="Coordinates of flats in a basis (paper Eq. 9/12)")
def math_coordinates(req: json_body(CoordinatesRequest), settings: SettingsDep) -> Response:
    basis = specs.build_basis(req.basis, req.k, req.d)
    flats = specs.flats_of(req.flats, req.k, req.d, "flats", settings.max_batch_rows)
    c = basis.coordinates_of(flats)
    out = {"weights": c.weights, "status": c.status, "residual": c.residual}
    if req.embed:
        from ..embedding import embed
        out["embedded"] = embed(c.weights)
    return JSONBytes(out)


@api.post("/math/project", response_model=ProjectResult, tags=["math"],
          dependencies=[ReadAccess], responses=COMMON_RESPONSES,
          openapi_extra=json_body_doc(ProjectRequest),
          summary="Projection of an affine combination of flats (paper Eq. 4-6)")
def math_project(req: json_body(ProjectRequest), settings: SettingsDep) -> Response:
    from .. import flats
    from .._validate import as_array

    Q, r = specs.flats_from(req.flats, req.k, req.d, "flats", settings.max_batch_rows,
                            validate=False)
    w = as_array(req.weights, "weights", ("n", Q.shape[0]))
    if w.shape[0] > settings.max_batch_rows:
        from .status import BatchTooLargeError
        raise BatchTooLargeError(f"{w.shape[0]} weight rows; the limit is {settings.max_batch_rows}")
    p = flats.affine_combination(w, Q, r, req.k)
    A, b = flats.to_parametric(p.Q, p.r, req.k)
    return JSONBytes({"Q": p.Q, "r": p.r, "A": A, "b": b, "gap": p.gap, "ambiguous": p.ambiguous})


# -- health and metrics -------------------------------------------------------------
@health.get("/healthz", response_model=Health, tags=["health"], summary="Liveness")
def healthz() -> Response:
    return JSONBytes({"status": "ok"})


@health.get("/readyz", response_model=Health, tags=["health"], summary="Readiness",
            description="200 once the stored fields are restored and the replica follows "
                        "the log; 503 while they load or the database is unreachable. A "
                        "field that failed (its restore, or a log entry it cannot apply) "
                        "does not make the replica unready (every replica would fail it "
                        "alike): it is listed in `failed_fields` (its requests get 503 "
                        "naming the error).",
            responses={503: {"model": Health, "description": "Stored fields still loading."}})
def readyz(registry: RegistryDep) -> Response:
    entries = registry.snapshot_entries()
    names = [e.name for e in entries if e.state == "loading"]
    failed = [e.name for e in entries if e.state == "failed"]
    body = {"fields": len(entries), "loading": len(names), "loading_fields": names,
            "failed": len(failed), "failed_fields": failed,
            "pid": os.getpid(), "backend": registry.storage.kind}
    try:
        body.update(registry.follower.lag() if registry.follower.started.is_set() else
                    {"position": None, "head": registry.storage.head(), "lag_entries": None,
                     "lag_seconds": None})
    except Exception as exc:  # the database is unreachable: not ready
        return JSONBytes({"status": "storage unavailable", "error": str(exc), **body},
                         status_code=503)
    if not registry.ready.is_set():
        return JSONBytes({"status": "loading", **body}, status_code=503)
    return JSONBytes({"status": "ready", **body})


@health.get("/metrics", tags=["health"], summary="Prometheus metrics",
            response_class=Response, dependencies=[ReadAccess],
            responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                             "description": "Prometheus text format."}})
def metrics(request: Request) -> Response:
    from .metrics import CONTENT_TYPE

    return Response(request.app.state.metrics.render(), media_type=CONTENT_TYPE)
