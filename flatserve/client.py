"""Python client of the flatserve HTTP service: NumPy in, NumPy out.

Bulk arrays travel as ``.npy`` / ``.npz`` bodies (see
:mod:`flatserve.service.http.codec` for the layouts); JSON only for small documents.

Example
-------
>>> from flatserve.client import Client                      # doctest: +SKIP
>>> with Client("http://127.0.0.1:8000") as c:               # doctest: +SKIP
...     c.create_field("scene", channels=3, exist_ok=True)
...     c.upload_rays("scene", origins, directions, colours, progress=True)
...     res = c.query_rays("scene", origins2, directions2)
...     res.values, res.inside

A light field's views and real captures (``flatserve[lightfield]`` for the latter):

>>> img = c.render("scene", {"orbit": {"yaw": 30}, "width": 64, "height": 64})  # doctest: +SKIP
>>> c.import_capture("room", "captures/room", stride=2)    # doctest: +SKIP

Uploads and queries larger than the server's limits (``GET /v1/limits``:
``max_batch_rows``, ``max_body_bytes``, ``max_json_bytes``) are sent as several
requests; each batch of an upload carries its own ``Idempotency-Key``
(``KEY.0``, ``KEY.1``, ... of the call's key), so a call repeated with the same
``idempotency_key`` after a failure stores the batches it had not stored and
replays the others: nothing lost, nothing twice.
"""
from __future__ import annotations

import functools
import gc
import hashlib
import importlib.util
import io
import math
import time
import uuid
from typing import Any, Callable, Union

import httpx
import numpy as np
import orjson

from . import _npy as _npy_mod
from .errors import FlatserveError, InvalidInputError
from .service.status import FieldExistsError, FieldNotFoundError, error_class
from .field import QueryResult
from .flats import FORMS, Flats, infer_form

NPY = "application/x-npy"
NPZ = "application/x-npz"
PNG = "image/png"

#: Statuses after which an idempotent request is retried, waiting ``Retry-After``:
#: 429 (a field's insert backlog is full), 503 (not ready, replica behind, database away)
RETRY_STATUSES = (429, 503)
#: Bytes of a binary body besides its rows (the ``.npy`` header, the ``.npz`` directory)
BODY_OVERHEAD = 4096
#: Bytes one number may take in a JSON body (orjson's longest float and a separator)
JSON_NUMBER_BYTES = 26
#: A progress bar's batches: uploads split into about this many when no
#: ``batch_rows`` is given (but never below :data:`PROGRESS_MIN_ROWS` rows each)
PROGRESS_BATCHES = 20
PROGRESS_MIN_ROWS = 10_000

#: ``progress`` of an upload: True (a tqdm bar on stderr), or a callable
#: ``progress(rows_done, rows_total)`` called after each batch
Progress = Union[bool, Callable[[int, int], Any], None]


class ServiceError(FlatserveError):
    """An error response of the service: ``status`` and ``detail`` as sent.

    The client raises it combined with the library class of the status
    (:func:`flatserve.service.status.error_class`, the inverse of
    :data:`flatserve.service.status.HTTP_STATUS`): a 404 is a
    :class:`~flatserve.service.status.FieldNotFoundError`, a 409 a
    :class:`~flatserve.service.status.FieldExistsError`, a 413 a
    :class:`~flatserve.service.status.LimitExceededError`, a 422 an
    :class:`~flatserve.errors.InvalidInputError` (``argument`` is the last
    element of ``detail[0].loc``), a 429 a
    :class:`~flatserve.service.status.BacklogFullError`, a 503 a
    :class:`~flatserve.service.status.NotReadyError`, a 507 a
    :class:`~flatserve.service.status.StorageFullError`; other statuses raise it alone.

    Attributes
    ----------
    status : int
        HTTP status.
    detail : Any
        The ``detail`` member of the response (the body's text if not JSON).
    """

    def __init__(self, status: int, detail: Any):
        super().__init__(f"HTTP {status}: {detail}")
        self.status = status
        self.detail = detail
        if isinstance(self, InvalidInputError):
            loc = None
            if isinstance(detail, list) and detail and isinstance(detail[0], dict):
                loc = detail[0].get("loc")
            self.argument = loc[-1] if loc else None


@functools.cache
def _error_type(status: int) -> type[ServiceError]:
    """``ServiceError`` combined with the library class of ``status`` (if any)."""
    base = error_class(status)
    if base is None:
        return ServiceError
    return type(base.__name__, (ServiceError, base),
                {"__module__": __name__, "__doc__": f"{base.__name__} reported by the service."})


def _load_npy(data: bytes) -> np.ndarray:
    """An .npy response as an array (no pickles; the header parse is cached)."""
    dtype, shape, fortran, off = _npy_mod.header(data)
    if dtype.hasobject:
        raise ValueError("object arrays are not accepted")
    return _npy_mod.from_bytes(data, dtype, shape, fortran, off)


def _npz(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _flat_arrays(flats: Flats | None, arrays: dict) -> tuple[str, dict[str, np.ndarray]]:
    """``(form, arrays)`` of a :class:`Flats` batch or of arrays given by name
    (sent as they are: the server validates them)."""
    if flats is not None:
        return flats.form, dict(flats.arrays)
    given = {k: v for k, v in arrays.items() if v is not None}
    form = infer_form(given)
    if form is None:
        raise InvalidInputError("give flats, or origins+directions, A+b, Q+r or points",
                                "origins")
    return form, {name: np.asarray(given.get(name), np.float64) for name in FORMS[form]}


def server_timing(resp: httpx.Response) -> dict[str, float]:
    """Seconds per phase from a response's ``Server-Timing`` header."""
    out = {}
    for part in resp.headers.get("server-timing", "").split(","):
        name, _, dur = part.strip().partition(";dur=")
        if name and dur:
            out[name] = float(dur) / 1e3
    return out


class Client:
    """Talks to one flatserve server.

    Parameters
    ----------
    base_url : str
        ``http://host:port``.
    api_key : str, optional
        Sent as ``Authorization: Bearer <key>``.
    timeout : float
        Seconds per request.
    retries : int
        Uploads and reads retried this many times on connection errors and on
        429 / 503 answers (after the answer's ``Retry-After``, at most
        ``max_retry_after`` seconds); uploads carry an ``Idempotency-Key``, so a
        retry never stores twice. Creates and deletes are never retried.
    max_retry_after : float
        Longest wait before a retry, whatever ``Retry-After`` says.
    http : httpx.Client, optional
        Use this client instead (e.g. a ``fastapi.testclient.TestClient``).
    """

    def __init__(self, base_url: str = "http://127.0.0.1:8000", *, api_key: str | None = None,
                 timeout: float = 120.0, retries: int = 2, max_retry_after: float = 30.0,
                 http: httpx.Client | None = None):
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        if http is None:
            self._http = httpx.Client(base_url=base_url, timeout=timeout, headers=headers)
            self._own = True
        else:
            self._http = http
            self._http.headers.update(headers)
            self._own = False
        self.retries = retries
        self.max_retry_after = max_retry_after
        self._limits: dict | None = None
        #: the last httpx.Response (headers such as ``Server-Timing``)
        self.last_response: httpx.Response | None = None

    def close(self) -> None:
        if self._own:
            self._http.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- plumbing -----------------------------------------------------------
    def _request(self, method: str, url: str, *, retry: bool = True, **kw) -> httpx.Response:
        attempts = 1 + (self.retries if retry else 0)
        for i in range(attempts):
            try:
                resp = self._http.request(method, url, **kw)
            except httpx.TransportError:
                if i + 1 == attempts:
                    raise
                time.sleep(0.2 * (i + 1))
                continue
            self.last_response = resp
            if resp.status_code in RETRY_STATUSES and i + 1 < attempts:
                time.sleep(self._retry_after(resp, i))
                continue
            if resp.status_code >= 400:
                try:
                    detail = resp.json().get("detail")
                except Exception:
                    detail = resp.text
                raise _error_type(resp.status_code)(resp.status_code, detail)
            return resp
        raise AssertionError("unreachable")

    def _retry_after(self, resp: httpx.Response, attempt: int) -> float:
        """Seconds to wait before retrying ``resp``: its ``Retry-After`` (seconds),
        else a short back-off; at most :attr:`max_retry_after`."""
        try:
            wait = float(resp.headers.get("retry-after", ""))
        except ValueError:
            wait = 0.2 * (attempt + 1)
        return min(max(wait, 0.0), self.max_retry_after)

    def limits(self) -> dict:
        """The server's request limits (``GET /v1/limits``, read once): ``max_batch_rows``,
        ``max_body_bytes``, ``max_json_bytes``, ``max_pending_samples``. A server of a
        version without the endpoint: ``{}`` (nothing is split)."""
        if self._limits is None:
            try:
                self._limits = self._request("GET", "/v1/limits").json()
            except FieldNotFoundError:  # an older server: 404
                self._limits = {}
        return self._limits

    def _rows_per_request(self, row_numbers: int, binary: bool, nrows: int,
                          batch_rows: int | None) -> int:
        """Most rows of one request: ``batch_rows`` if given, within the server's limits
        (rows, and body bytes at ``row_numbers`` float64 numbers per row)."""
        lim = self.limits()
        cap = lim.get("max_batch_rows", nrows)
        if binary and "max_body_bytes" in lim:
            cap = min(cap, (lim["max_body_bytes"] - BODY_OVERHEAD) // (8 * row_numbers))
        if not binary and "max_json_bytes" in lim:
            cap = min(cap, (lim["max_json_bytes"] - 1024) // (JSON_NUMBER_BYTES * row_numbers))
        if batch_rows is not None:
            if batch_rows < 1:
                raise InvalidInputError(f"batch_rows: at least 1, got {batch_rows}", "batch_rows")
            cap = min(cap, batch_rows)
        return max(int(cap), 1)

    # -- service ------------------------------------------------------------
    def health(self) -> dict:
        return self._request("GET", "/healthz").json()

    def ready(self) -> bool:
        try:
            return self._http.get("/readyz").status_code == 200
        except httpx.TransportError:
            return False

    def wait_ready(self, timeout: float = 60.0, interval: float = 0.05) -> None:
        """Block until ``/readyz`` answers 200 (raises TimeoutError)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.ready():
                return
            time.sleep(interval)
        raise TimeoutError(f"server not ready after {timeout} s")

    def metrics(self) -> str:
        return self._request("GET", "/metrics").text

    # -- fields -------------------------------------------------------------
    def create_field(self, name: str, *, k: int = 1, d: int = 3, channels: int = 1,
                     basis: dict | None = None, oriented: bool | None = None,
                     roundtrip_tol: float | None = None, unit: float | str | None = None,
                     copies: int | None = None, tiles: int | str | None = None,
                     rig=None, exist_ok: bool = False,
                     verbose: bool = False) -> dict:
        """Create a field; returns its description (``verbose``: with the basis flats
        and every chart of an atlas, see :meth:`describe`).

        ``exist_ok=True``: a field of that name already there is not an error if it
        has the same ``k``, ``d``, ``channels`` (and ``oriented`` and ``rig``, when
        given): its description is returned (its basis is not compared); one that
        differs raises :class:`~flatserve.service.status.FieldExistsError` naming
        what differs.

        ``basis`` left out: a covering atlas (every orientation accepted), of rays
        when ``oriented`` (k = 1; uploads and queries must then be rays). One chart:
        ``{"kind": "tangent_simplex", "scale": 0.01}`` or ``{"kind": "flats", "Q":
        Q.tolist(), "r": r.tolist()}``. An atlas for given flats: ``{"kind": "atlas",
        "atlas": "samples", "samples": {"origins": ..., "directions": ...}}``.
        ``unit``: an atlas's unit of length (the shift that counts as much as a turn
        of one radian; for rays of an object about its half-size); left out or
        ``"fit"``: chosen from the first batch's values (held-out validation among
        multiples of its flats' own unit), ``"data"``: from its flats alone.
        ``copies``: a server in cluster mode keeps that many copies of each shard,
        on different nodes (default 1). ``tiles``: a one-chart field's triangulation
        in that many tiles, built on the server's cores at once (default 1; ``"auto"``:
        one per core once the field is large enough). ``rig``: a light field of a
        capture with depth (oriented rays in R^3, the last of its ``channels`` the
        depth channel): the capture's cameras, ``{"eyes": (m, 3), "center": (3,)}``
        or a :class:`~flatserve.lightfield.rig.DepthRig`; its renders go through
        the depth (:meth:`import_capture` gives it when the capture wants it)."""
        body: dict[str, Any] = {"name": name, "k": k, "d": d, "channels": channels}
        if rig is not None:
            rig = _rig_body(rig)
            body["rig"] = rig
        if copies is not None:
            body["copies"] = copies
        if tiles is not None:
            body["tiles"] = tiles
        if basis is not None:
            body["basis"] = basis
        if oriented is not None:
            body["oriented"] = oriented
        if roundtrip_tol is not None:
            body["roundtrip_tol"] = roundtrip_tol
        if unit is not None:
            body["unit"] = unit
        try:
            return self._request("POST", "/v1/fields", json=body, retry=False,
                                 params={"verbose": "true"} if verbose else {}).json()
        except FieldExistsError as exc:
            if not exist_ok:
                raise
            try:
                info = self.describe(name, verbose=verbose)
            except FieldNotFoundError:  # the 409 was another (max_fields), or it went away
                raise exc from None
            want = {"k": k, "d": d, "channels": channels}
            if oriented is not None:
                want["oriented"] = oriented
            differ = {key: (info.get(key), v) for key, v in want.items() if info.get(key) != v}
            if rig is not None and not _same_rig(info.get("rig"), rig):
                differ["rig"] = (_rig_text(info.get("rig")), _rig_text(rig))
            if differ:
                raise _error_type(409)(409, f"field {name!r} exists with " + ", ".join(
                    f"{key}={have!r} (asked {v!r})" for key, (have, v) in differ.items())) from None
            return info

    def list_fields(self) -> list[dict]:
        return self._request("GET", "/v1/fields").json()["fields"]

    def describe(self, name: str, *, min_position: int | None = None,
                 verbose: bool = False) -> dict:
        """The field's description; ``min_position``: as this replica sees it once it
        has applied that log position (read-your-writes, see :meth:`query`).
        ``verbose``: also the basis flats (``basis.Q``, ``basis.r``) and, of an atlas,
        every chart (``charts``); by default a summary (``ncharts``, ``atlas``)."""
        params = {} if min_position is None else {"min_position": str(int(min_position))}
        if verbose:
            params["verbose"] = "true"
        return self._request("GET", f"/v1/fields/{name}", params=params).json()

    def delete_field(self, name: str) -> None:
        self._request("DELETE", f"/v1/fields/{name}", retry=False)

    def batches(self, name: str) -> list[dict]:
        return self._request("GET", f"/v1/fields/{name}/batches").json()["batches"]

    def snapshot(self, name: str) -> dict:
        return self._request("POST", f"/v1/fields/{name}/snapshot").json()

    def export_field(self, name: str, path=None) -> bytes:
        """The field as one file (``GET /v1/fields/{name}/export``: its definition and
        every stored batch, an ``.npz``); written to ``path`` too when given."""
        data = self._request("GET", f"/v1/fields/{name}/export").content
        if path is not None:
            with open(path, "wb") as f:
                f.write(data)
        return data

    def import_field(self, name: str, export) -> dict:
        """Create field ``name`` from an export (bytes, or the path of the file) of this or
        another server; it answers bit for bit as the exported field. Safe to repeat
        after a failure: batches already stored are replayed, not stored twice."""
        if not isinstance(export, (bytes, bytearray, memoryview)):
            with open(export, "rb") as f:
                export = f.read()
        return self._request("POST", f"/v1/fields/{name}/import", content=bytes(export),
                             headers={"Content-Type": NPZ}).json()

    # -- samples ------------------------------------------------------------
    def upload(self, name: str, values, flats: Flats | None = None, *, origins=None,
               directions=None, A=None, b=None, Q=None, r=None, points=None,
               idempotency_key: str | None = None, binary: bool = True,
               wait: bool = True, batch_rows: int | None = None,
               progress: Progress = None) -> dict:
        """Upload samples; returns the service's report (accepted, rejected indices and
        reasons, nsamples, batch, indexed, position).

        More rows than one request may carry (the server's ``max_batch_rows``, or its
        body limits) are sent as several batches of at most ``batch_rows`` rows, in
        order; the report then sums them: ``accepted`` and ``duplicates`` added up,
        ``rejected`` as row indices of the whole upload, ``batch``, ``nsamples``
        and ``position`` of the last batch, ``batches`` lists every batch number,
        ``replayed`` is true when every batch was. Each batch has its own
        Idempotency-Key (``KEY.0``, ``KEY.1``, ...; one batch: ``KEY``): a fresh
        ``KEY`` is generated when none is given, so retries are safe; repeat a
        failed call with the same ``idempotency_key`` (and the same ``batch_rows``
        and ``progress``, which decide the split) to store what it had not stored;
        a call that splits otherwise under the same key is refused (422), never
        stored twice.

        ``progress``: True shows a progress bar (tqdm, on stderr); a callable is
        called as ``progress(rows_done, rows_total)`` after each batch. Without
        ``batch_rows`` a progress bar splits the upload into about 20 batches (of
        at least 10,000 rows).

        ``wait=False``: the service acknowledges once a batch is durably stored
        and its coordinates known, and triangulates it in the background
        (``report["indexed"]`` is False); see :meth:`wait_indexed`.
        """
        form, arrays = _flat_arrays(flats, dict(origins=origins, directions=directions, A=A,
                                                b=b, Q=Q, r=r, points=points))
        values = np.asarray(values, np.float64)
        if values.ndim == 1:
            values = values[:, None]
        key = idempotency_key or uuid.uuid4().hex
        n = values.shape[0]
        rows = max(n, 1)  # (zero rows: one request, which the service refuses, 422)
        if n:
            width = values.shape[1] + sum(math.prod(a.shape[1:]) for a in arrays.values())
            if progress and batch_rows is None:
                batch_rows = max(PROGRESS_MIN_ROWS, -(-n // PROGRESS_BATCHES))
            rows = self._rows_per_request(max(width, 1), binary, n, batch_rows)
        starts = list(range(0, n, rows)) or [0]
        report = _Reports(len(starts) > 1)
        with _progress_of(progress, n, name) as tick:
            for i, s0 in enumerate(starts):
                part = slice(s0, s0 + rows)
                one = self._upload_batch(
                    name, form, {k: v[part] for k, v in arrays.items()}, values[part],
                    key if len(starts) == 1 else f"{key}.{i}", binary, wait)
                report.add(one, s0)
                tick(min(s0 + rows, n))
        return report.result()

    def _upload_batch(self, name: str, form: str, arrays: dict, values: np.ndarray, key: str,
                      binary: bool, wait: bool) -> dict:
        """One ``POST .../samples`` of one batch under Idempotency-Key ``key``."""
        headers = {"Idempotency-Key": key}
        params = {"form": form}
        if not wait:
            params["wait"] = "false"
        if not binary:
            body = {"form": form, "values": np.ascontiguousarray(values),
                    **{k: np.ascontiguousarray(v) for k, v in arrays.items()}}
            headers["Content-Type"] = "application/json"
            return self._request("POST", f"/v1/fields/{name}/samples", params=params,
                                 content=orjson.dumps(body, option=orjson.OPT_SERIALIZE_NUMPY),
                                 headers=headers).json()
        content, ctype = self._encode(form, arrays, values)
        headers["Content-Type"] = ctype
        return self._request("POST", f"/v1/fields/{name}/samples", params=params,
                             content=content, headers=headers).json()

    def wait_indexed(self, name: str, batch: int | None = None, timeout: float = 60.0,
                     interval: float = 0.02) -> dict:
        """Poll the field until batch ``batch`` (default: every stored batch) is
        indexed, i.e. visible to queries; returns the field's description."""
        end = time.monotonic() + timeout
        while True:
            info = self.describe(name)
            target = info["storage"]["last_batch"] if batch is None else batch
            if info["indexed_batch"] >= target:
                return info
            if time.monotonic() > end:
                raise TimeoutError(f"batch {target} of {name!r} not indexed after {timeout} s "
                                   f"(indexed up to {info['indexed_batch']})")
            time.sleep(interval)

    def upload_rays(self, name: str, origins, directions, values, **kw) -> dict:
        return self.upload(name, values, origins=origins, directions=directions, **kw)

    def upload_parametric(self, name: str, A, b, values, **kw) -> dict:
        return self.upload(name, values, A=A, b=b, **kw)

    def upload_flats(self, name: str, Q, r, values, **kw) -> dict:
        return self.upload(name, values, Q=Q, r=r, **kw)

    def upload_points(self, name: str, points, values, **kw) -> dict:
        """Upload samples at points (n, d) of a field of points (k = 0)."""
        return self.upload(name, values, points=points, **kw)

    @staticmethod
    def _encode(form, arrays, values=None) -> tuple[bytes, str]:
        if form in ("rays", "points"):  # rows of numbers: one .npy, columns side by side
            cols = [arrays[name] for name in FORMS[form]]
            if values is not None:
                cols.append(values)
            n = {c.shape[0] for c in cols if c.ndim == 2}
            if len(n) == 1 and all(c.ndim == 2 for c in cols):
                return _npy_mod.columns_to_buffer(cols).tobytes(), NPY
        out = dict(arrays)
        if values is not None:
            out["values"] = values
        return _npz(out), NPZ

    def query(self, name: str, flats: Flats | None = None, *, origins=None, directions=None,
              A=None, b=None, Q=None, r=None, points=None, weights: bool = False, outside: str = "nan",
              order: str = "hilbert", binary: bool = True,
              min_position: int | None = None, batch_rows: int | None = None,
              interpolant: str = "linear") -> QueryResult:
        """Interpolate the field at a batch of flats (a :class:`Flats`, or arrays by name).

        ``interpolant``: ``"linear"`` (the paper's) or ``"gradient"`` (slopes fitted
        to each vertex's nearest samples: :meth:`flatserve.Field.query`).

        More flats than one request may carry (the server's ``max_batch_rows`` or body
        limits; or ``batch_rows``) are sent as several requests, answered in order.

        ``min_position``: read-your-writes across replicas: the ``position`` of an
        upload's report (on any replica); the server answers once it has applied
        it (503 :class:`~flatserve.service.status.ReplicaBehindError` after its wait).

        Returns the library's :class:`flatserve.QueryResult`, ``status`` filled
        (the ``.npy`` answer is asked with ``status=true``: its last column), and
        ``ids`` and ``weights`` with ``weights``."""
        form, arrays = _flat_arrays(flats, dict(origins=origins, directions=directions, A=A,
                                                b=b, Q=Q, r=r, points=points))
        params = {"form": form, "outside": outside, "order": order,
                  "weights": "true" if weights else "false"}
        if interpolant != "linear":
            params["interpolant"] = str(interpolant)
        if min_position is not None:
            params["min_position"] = str(int(min_position))
        n = len(next(iter(arrays.values())))
        width = sum(math.prod(a.shape[1:]) for a in arrays.values())
        rows = self._rows_per_request(max(width, 1), binary, n, batch_rows) if n else n
        if n > rows:
            parts = [self._query_batch(name, form, {k: v[s0:s0 + rows] for k, v in arrays.items()},
                                       params, weights, binary) for s0 in range(0, n, rows)]
            return QueryResult(**{
                f: None if getattr(parts[0], f) is None else
                np.concatenate([getattr(p, f) for p in parts])
                for f in ("values", "inside", "status", "ids", "weights")})
        return self._query_batch(name, form, arrays, params, weights, binary)

    def _query_batch(self, name: str, form: str, arrays: dict, params: dict, weights: bool,
                     binary: bool) -> QueryResult:
        """One ``POST .../query``."""
        url = f"/v1/fields/{name}/query"
        if not binary:
            body = {"form": form, **{k: v.tolist() for k, v in arrays.items()}}
            j = self._request("POST", url, params=params, json=body).json()
            vals = np.array([[np.nan if x is None else x for x in row] for row in j["values"]],
                            dtype=np.float64).reshape(len(j["inside"]), -1)
            return QueryResult(vals, np.asarray(j["inside"], bool),
                               np.asarray(j["status"], np.int8),
                               np.asarray(j["ids"], np.int64) if weights else None,
                               np.array(j["weights"], dtype=np.float64) if weights else None)
        content, ctype = self._encode(form, arrays)
        accept = NPZ if weights else NPY
        resp = self._request("POST", url, params=params if weights else {**params, "status": "true"},
                             content=content, headers={"Content-Type": ctype, "Accept": accept})
        if weights:
            with np.load(io.BytesIO(resp.content), allow_pickle=False) as z:
                return QueryResult(z["values"], z["inside"], z["status"], z["ids"], z["weights"])
        arr = _load_npy(resp.content)  # rows values | inside | status
        return QueryResult(arr[:, :-2], arr[:, -2] != 0, arr[:, -1].astype(np.int8))

    def query_rays(self, name: str, origins, directions, **kw) -> QueryResult:
        return self.query(name, origins=origins, directions=directions, **kw)

    def query_parametric(self, name: str, A, b, **kw) -> QueryResult:
        return self.query(name, A=A, b=b, **kw)

    def query_flats(self, name: str, Q, r, **kw) -> QueryResult:
        return self.query(name, Q=Q, r=r, **kw)

    def query_points(self, name: str, points, **kw) -> QueryResult:
        """Interpolate a field of points (k = 0) at points (n, d)."""
        return self.query(name, points=points, **kw)

    # -- stateless math ---------------------------------------------------------
    def coordinates(self, *, k: int = 1, d: int = 3, basis: dict | None = None,
                    embed: bool = False, **flats) -> dict:
        """Coordinates of flats (``Q``/``r``, ``A``/``b``, ``origins``/``directions`` or
        ``points``)."""
        body = {"k": k, "d": d, "embed": embed,
                "flats": {kk: np.asarray(v, np.float64).tolist() for kk, v in flats.items()}}
        if basis is not None:
            body["basis"] = basis
        j = self._request("POST", "/v1/math/coordinates", json=body).json()
        return {kk: (np.array(v, dtype=np.float64) if kk != "status" else np.asarray(v, np.int8))
                for kk, v in j.items() if v is not None}

    def project(self, weights, *, k: int = 1, d: int = 3, **flats) -> dict:
        body = {"k": k, "d": d, "weights": np.asarray(weights, np.float64).tolist(),
                "flats": {kk: np.asarray(v, np.float64).tolist() for kk, v in flats.items()}}
        j = self._request("POST", "/v1/math/project", json=body).json()
        return {kk: np.array(v, dtype=bool if kk == "ambiguous" else np.float64)
                for kk, v in j.items()}

    # -- light fields -------------------------------------------------------------
    def render(self, name: str, camera=None, *, format: str = "npy", **spec):
        """Render a camera's view of a light field (``POST /v1/fields/{name}/render``).

        Parameters
        ----------
        name : str
            A field of lines in R^3 (k = 1, d = 3).
        camera : dict, PinholeCamera, Camera or None
            A dict: the render body's camera members as the service takes them
            (``{"orbit": {...}}``, ``{"eye": [...], "target": [...]}``,
            ``{"nerf": {...}}``, ``{"colmap": {...}}``, with ``width``,
            ``height``, ``supersample`` ...). A
            :class:`~flatserve.lightfield.camera.PinholeCamera` is sent as its
            COLMAP pose (:meth:`~flatserve.lightfield.camera.PinholeCamera.to_colmap`)
            with its ``supersample``; a :class:`~flatserve.lightfield.Camera` as
            its ``eye``, ``rotation``, ``focal``, ``width``, ``height`` and
            ``supersample``. None: the service's default camera.
        format : {"npy", "png"}
            The answer's encoding.
        **spec
            More members of the body, over the camera's (``width``, ``height``,
            ``supersample``, ``fill``, ``interpolant``).

        Returns
        -------
        numpy.ndarray or bytes
            ``"npy"``: float32 (H, W, C), NaN where no ray of a pixel has a value;
            ``"png"``: the PNG file's bytes.

        Raises
        ------
        InvalidInputError
            A camera the service refuses (422; ``argument`` names the member,
            e.g. ``transform_matrix`` of ``nerf``), or a ``format`` other than
            the two.
        """
        if format not in ("npy", "png"):
            raise InvalidInputError(f"format: expected 'npy' or 'png', got {format!r}", "format")
        body = {**_camera_body(camera), **spec, "format": format}
        resp = self._request(
            "POST", f"/v1/fields/{name}/render",
            content=orjson.dumps(body, option=orjson.OPT_SERIALIZE_NUMPY),
            headers={"Content-Type": "application/json",
                     "Accept": NPY if format == "npy" else PNG})
        return _load_npy(resp.content) if format == "npy" else resp.content

    def import_capture(self, name: str, path, *, format: str | None = None,
                       stride: int | None = None, target_rays: int | None = None,
                       holdout=(), background=0.0, batch_rays: int | None = None,
                       progress: Progress = True, create: bool = True,
                       depth: bool | None = None, **field_options) -> dict:
        """Upload a real capture (posed photographs) as a light field: one ray per pixel.

        Reads the capture (:func:`flatserve.lightfield.capture.read_capture`: a NeRF
        ``transforms.json`` or a COLMAP text model beside its images), creates the
        field (:func:`~flatserve.lightfield.capture.field_options`, updated by
        ``field_options``; an existing field of the same kind is kept, so an
        import resumes) and uploads the pixels' rays and colours in batches
        (:func:`~flatserve.lightfield.capture.capture_batches`: one image at a
        time, so memory is bounded by a batch, never the whole capture).

        On a sparse rig all around an object
        (:func:`flatserve.lightfield.rig.wants_depth`, or ``depth=True``) each
        pixel's depth too, from the capture's own photographs
        (:func:`flatserve.lightfield.depth.depth_map`), as the field's last
        channel, and the field gets the ``rig`` its renders go through.

        Each batch carries an Idempotency-Key derived from the field's name, the
        capture's format, its frames' names and poses, ``stride``, the channels,
        the batch size and the depth's rig (``capture-<hash>.<batch>``,
        :func:`capture_key`): the same call repeated after an interruption
        replays what was stored (the service answers ``replayed``) and stores
        only the rest; nothing is stored twice.

        Parameters
        ----------
        name : str
            The field.
        path : str or os.PathLike
            The capture's directory (or its ``transforms.json``).
        format : {"nerf", "colmap"}, optional
            Default: found from the files.
        stride : int, optional
            Every ``stride``-th pixel of every ``stride``-th row (default 1).
        target_rays : int, optional
            Instead of ``stride``: the smallest stride giving at most this many rays.
        holdout : iterable of str
            Frames (by name) left out, e.g. to compare renders with them.
        background : float or (3,) float
            Grey level or RGB colour in [0, 1] behind transparent pixels, when
            RGBA images are imported into a field of fewer channels (``channels=3``
            or 1; :func:`~flatserve.lightfield.capture.capture_batches`). Part of
            the keys when not 0.
        batch_rays : int, optional
            Rays per batch (default: the capture module's ``BATCH_RAYS``; a batch more
            than a request may carry is sent in parts, as :meth:`upload` does). Part of
            the keys: resume with the same.
        progress : bool or callable
            True: a progress bar over the rays (tqdm, on stderr); a callable is
            called as ``progress(rays_done, rays_total)`` after each batch.
        create : bool
            Create the field (False: it must exist).
        depth : bool, optional
            Give the field the depth channel and the capture's ``rig`` (True),
            not (False), or as :func:`~flatserve.lightfield.capture.field_options`
            decides (None: on a sparse rig all around, where the depth-guided
            render wins; not on a forward-facing rig, where the field alone does).
        **field_options
            Keyword arguments of :meth:`create_field` over the capture's own
            (``channels``: the colour channels, the depth channel not counted;
            ``basis``, ``unit``, ``oriented`` ...).

        Returns
        -------
        dict
            ``field``, ``format``, ``frames`` (imported), ``stride``, ``depth``
            (whether the batches carry the depth channel), ``rays`` (sent),
            ``stored`` (accepted by batches stored now), ``rejected`` (rows
            refused by batches stored now), ``batches``, ``replayed`` (batches
            stored before, by an earlier run), ``nsamples`` (the field's, after the
            last batch) and ``key`` (the keys' stem).

        Raises
        ------
        ImportError
            Pillow is missing (``pip install 'flatserve[lightfield]'``).
        flatserve.lightfield.capture.CaptureError
            A bad capture, naming the file and the field.
        InvalidInputError
            ``stride`` and ``target_rays`` both given, or a bad one; ``depth``
            not a bool or None, or True for a capture of one frame.
        """
        cap = _capture_module()
        if stride is not None and target_rays is not None:
            raise InvalidInputError("stride: give stride or target_rays, not both", "stride")
        for arg, v in (("stride", stride), ("target_rays", target_rays),
                       ("batch_rays", batch_rays)):
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer))
                                  or v < 1):
                raise InvalidInputError(f"{arg}: expected a positive integer, got {v!r}", arg)
        cap.check_background(background)
        capture = cap.read_capture(path, format=format)
        if isinstance(holdout, str):
            holdout = (holdout,)
        holdout = tuple(holdout)
        if holdout:
            try:
                capture = capture.without(holdout)
            except InvalidInputError as exc:  # names unknown, or every frame held out
                raise InvalidInputError(f"holdout: {str(exc).removeprefix('names: ')}",
                                        "holdout") from None
        if target_rays is not None:
            stride = capture.stride_for(int(target_rays))
        stride = int(stride or 1)
        # the capture's choices (channels: the colours, plus the depth channel with a
        # rig), the caller's over them; the colours asked go to field_options itself
        options = cap.field_options(capture, channels=field_options.get("channels"), depth=depth)
        channels = int(options["channels"]) - ("rig" in options)  # the colour channels
        options.update((k, v) for k, v in field_options.items() if k != "channels")
        rig = options.get("rig")
        if rig is not None and not isinstance(rig, dict):  # (a DepthRig given)
            rig = rig.to_dict()
        options["channels"] = channels + (rig is not None)
        if create:
            self.create_field(name, exist_ok=True, **options)
        if batch_rays is None:  # fixed, not the server's limits: the keys must not change
            batch_rays = cap.BATCH_RAYS  # (a batch too large for a request is split by upload)
        depth_rig = None if rig is None else _depth_module().DepthRig.from_dict(rig)
        key = capture_key(name, capture, stride=stride, channels=channels,
                          batch_rays=int(batch_rays), background=background,
                          rig=None if depth_rig is None else depth_rig.to_dict())
        total = capture.nrays(stride)
        out = {"field": name, "format": capture.format, "frames": len(capture.frames),
               "stride": stride, "depth": depth_rig is not None, "rays": 0, "stored": 0,
               "rejected": 0, "batches": 0, "replayed": 0, "nsamples": None, "key": key}
        with _progress_of(progress, total, name, unit="rays", verb="import") as tick:
            for batch in cap.capture_batches(capture, stride=stride, channels=channels,
                                             background=background, batch_rays=int(batch_rays),
                                             depth=depth_rig):
                rep = self.upload(name, batch.values, origins=batch.origins,
                                  directions=batch.directions,
                                  idempotency_key=f"{key}.{batch.index}")
                n = int(batch.values.shape[0])
                out["rays"] += n
                out["batches"] += 1
                if rep.get("replayed"):
                    out["replayed"] += 1
                else:
                    out["stored"] += int(rep["accepted"])
                    out["rejected"] += len(rep["rejected"])
                out["nsamples"] = rep.get("nsamples")
                tick(out["rays"])
                # each sent body stays reachable from httpx's request objects, which
                # refer to each other in cycles that only a full collection frees (and
                # large bytes hardly trigger one): without this the importer's peak grew
                # by about a body a batch (3M rays: +242 MiB against +78 MiB,
                # docs/capture-speed.md)
                del batch, rep
                gc.collect()
        return out


def _camera_body(camera) -> dict:
    """The camera members of a render body (see :meth:`Client.render`)."""
    if camera is None:
        return {}
    if isinstance(camera, dict):
        return dict(camera)
    if hasattr(camera, "to_colmap"):  # a PinholeCamera: its pose in COLMAP's convention
        return {"colmap": camera.to_colmap(), "supersample": int(camera.supersample)}
    if hasattr(camera, "focal") and hasattr(camera, "to_dict"):  # a lightfield.Camera
        return camera.to_dict()
    raise InvalidInputError(f"camera: expected a dict, a PinholeCamera or a Camera, got "
                            f"{type(camera).__name__}", "camera")


def _rig_body(rig) -> dict:
    """A create request's ``rig`` member: a dict (its arrays as lists) or a
    :class:`~flatserve.lightfield.rig.DepthRig`; anything else is sent as given,
    for the service to name what is wrong."""
    if hasattr(rig, "to_dict") and not isinstance(rig, dict):
        rig = rig.to_dict()
    if isinstance(rig, dict):
        return {k: v.tolist() if isinstance(v, np.ndarray) else v for k, v in rig.items()}
    return rig


def _same_rig(have, want) -> bool:
    """Whether a described field's ``rig`` is the one asked (the same numbers)."""
    if not isinstance(have, dict) or not isinstance(want, dict):
        return have == want
    try:
        return all(np.array_equal(np.asarray(have[k], np.float64), np.asarray(want[k], np.float64))
                   for k in ("eyes", "center"))
    except (KeyError, TypeError, ValueError):
        return False


def _rig_text(rig) -> str:
    """A rig in a few words (an error's): its cameras and centre."""
    if rig is None:
        return "none"
    try:
        return (f"{len(rig['eyes'])} eyes, center "
                f"{np.asarray(rig['center'], np.float64).round(6).tolist()}")
    except (KeyError, TypeError, ValueError):
        return repr(rig)[:80]


def _depth_module():
    """:mod:`flatserve.lightfield.depth` (the lightfield extra)."""
    from .lightfield import depth

    return depth


def _capture_module():
    """:mod:`flatserve.lightfield.capture`, imported when a capture is read (Pillow is in
    the lightfield extra, not the client's)."""
    if importlib.util.find_spec("PIL") is None:
        raise ImportError("reading a capture's images needs Pillow: pip install "
                          "'flatserve[lightfield]'")
    from .lightfield import capture

    return capture


def capture_key(name: str, capture, *, stride: int, channels: int, batch_rays: int,
                background=0.0, rig: dict | None = None) -> str:
    """The stem of the Idempotency-Keys of a capture's import (:meth:`Client.import_capture`).

    ``capture-`` and 24 hex digits of a SHA-256 of the field's name, the capture's
    format, its frames' names and poses, ``stride``, ``channels``, ``batch_rays``,
    ``background`` when it is not 0 (it changes RGBA pixels' values), and ``rig``
    and the depth's parameters (:data:`flatserve.lightfield.depth.DEPTH_METHOD`)
    when the batches carry the depth channel (an import with depth and one
    without are different batches); batch ``i`` is sent under ``<stem>.<i>``.
    Not the images' pixels: a frame whose image changed under the same key is
    refused by the service (its content differs), never stored twice.

    Parameters
    ----------
    name : str
        The field.
    capture : flatserve.lightfield.capture.Capture
    stride, channels, batch_rays : int
        As the import's (``channels``: the colour channels).
    background : float or (3,) float
    rig : dict, optional
        The depth's rig (:meth:`flatserve.lightfield.rig.DepthRig.to_dict`);
        None: no depth channel (the keys of imports before it existed).

    Returns
    -------
    str
    """
    doc = {"field": name, "format": capture.format, "stride": int(stride),
           "channels": int(channels), "batch_rays": int(batch_rays),
           "frames": [[f.name, f.camera.to_dict()] for f in capture.frames]}
    bg = _capture_module().check_background(background)
    if np.any(bg != 0):
        doc["background"] = bg.tolist()
    if rig is not None:
        from .lightfield.depth import DEPTH_METHOD

        doc["rig"] = {"eyes": np.asarray(rig["eyes"], np.float64).tolist(),
                      "center": np.asarray(rig["center"], np.float64).tolist()}
        doc["depth"] = DEPTH_METHOD
    digest = hashlib.sha256(orjson.dumps(doc, option=orjson.OPT_SERIALIZE_NUMPY)).hexdigest()
    return f"capture-{digest[:24]}"


class _Reports:
    """The report of an upload sent as several batches (see :meth:`Client.upload`)."""

    def __init__(self, several: bool):
        self.several = several
        self.parts: list[tuple[dict, int]] = []

    def add(self, report: dict, first_row: int) -> None:
        self.parts.append((report, first_row))

    def result(self) -> dict:
        if not self.several:
            return self.parts[0][0]
        last = dict(self.parts[-1][0])
        reps = [p for p, _ in self.parts]
        dups = [p.get("duplicates") for p in reps]
        last.update(
            batches=[p["batch"] for p in reps],
            accepted=sum(p["accepted"] for p in reps),
            rejected=[i + s0 for p, s0 in self.parts for i in p["rejected"]],
            reasons=[t for p in reps for t in p["reasons"]],
            duplicates=None if any(d is None for d in dups) else sum(dups),
            indexed=all(p.get("indexed", True) for p in reps),
            replayed=all(p.get("replayed", False) for p in reps),
            position=max(p.get("position", 0) for p in reps))
        return last


class _progress_of:
    """``with _progress_of(progress, total, name) as tick``: ``tick(rows_done)`` after
    each batch updates a tqdm bar (``progress=True``) or calls ``progress``."""

    def __init__(self, progress: Progress, total: int, name: str, *, unit: str = "rows",
                 verb: str = "upload"):
        self.progress, self.total, self.name = progress, total, name
        self.unit, self.verb = unit, verb
        self.bar = None

    def __enter__(self) -> Callable[[int], None]:
        if self.progress is True:
            try:
                from tqdm.auto import tqdm
            except ImportError:
                raise ImportError("progress=True needs tqdm: pip install tqdm (the client "
                                  "extra has it), or pass a callable") from None
            self.bar = tqdm(total=self.total, unit=self.unit, unit_scale=True,
                            desc=f"{self.verb} {self.name}")
            return lambda done: self.bar.update(done - self.bar.n)
        if callable(self.progress):
            return lambda done: self.progress(done, self.total)
        return lambda done: None

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.close()
