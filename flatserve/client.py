"""Python client of the flatserve HTTP service: NumPy in, NumPy out.

Bulk arrays travel as ``.npy`` / ``.npz`` bodies (see
:mod:`flatserve.service.codec` for the layouts); JSON only for small documents.

Example
-------
>>> from flatserve.client import Client                      # doctest: +SKIP
>>> with Client("http://127.0.0.1:8000") as c:               # doctest: +SKIP
...     c.create_field("scene", channels=3)
...     c.upload_rays("scene", origins, directions, colours)
...     res = c.query_rays("scene", origins2, directions2)
...     res.values, res.inside
"""
from __future__ import annotations

import functools
import io
import time
import uuid
from typing import Any

import httpx
import numpy as np
import orjson

from . import _npy as _npy_mod
from .errors import FlatserveError, InvalidInputError
from .service.status import error_class
from .field import QueryResult
from .flats import FORMS, Flats, infer_form

NPY = "application/x-npy"
NPZ = "application/x-npz"


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
        raise InvalidInputError("give flats, or origins+directions, A+b or Q+r", "origins")
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
        Uploads and reads retried this many times on connection errors
        (uploads carry an ``Idempotency-Key``, so a retry never stores twice).
    http : httpx.Client, optional
        Use this client instead (e.g. a ``fastapi.testclient.TestClient``).
    """

    def __init__(self, base_url: str = "http://127.0.0.1:8000", *, api_key: str | None = None,
                 timeout: float = 120.0, retries: int = 2, http: httpx.Client | None = None):
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        if http is None:
            self._http = httpx.Client(base_url=base_url, timeout=timeout, headers=headers)
            self._own = True
        else:
            self._http = http
            self._http.headers.update(headers)
            self._own = False
        self.retries = retries
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
            if resp.status_code >= 400:
                try:
                    detail = resp.json().get("detail")
                except Exception:
                    detail = resp.text
                raise _error_type(resp.status_code)(resp.status_code, detail)
            return resp
        raise AssertionError("unreachable")

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
                     roundtrip_tol: float | None = None, unit: float | None = None) -> dict:
        """Create a field; returns its description.

        ``basis`` left out: a covering atlas (every orientation accepted), of rays
        when ``oriented`` (k = 1; uploads and queries must then be rays). One chart:
        ``{"kind": "tangent_simplex", "scale": 0.01}`` or ``{"kind": "flats", "Q":
        Q.tolist(), "r": r.tolist()}``. An atlas for given flats: ``{"kind": "atlas",
        "atlas": "samples", "samples": {"origins": ..., "directions": ...}}``.
        ``unit``: an atlas's unit of length (the shift that counts as much as a turn
        of one radian; for rays of an object about its half-size; default 1)."""
        body: dict[str, Any] = {"name": name, "k": k, "d": d, "channels": channels}
        if basis is not None:
            body["basis"] = basis
        if oriented is not None:
            body["oriented"] = oriented
        if roundtrip_tol is not None:
            body["roundtrip_tol"] = roundtrip_tol
        if unit is not None:
            body["unit"] = unit
        return self._request("POST", "/v1/fields", json=body, retry=False).json()

    def list_fields(self) -> list[dict]:
        return self._request("GET", "/v1/fields").json()["fields"]

    def describe(self, name: str, *, min_position: int | None = None) -> dict:
        """The field's description; ``min_position``: as this replica sees it once it
        has applied that log position (read-your-writes, see :meth:`query`)."""
        params = {} if min_position is None else {"min_position": str(int(min_position))}
        return self._request("GET", f"/v1/fields/{name}", params=params).json()

    def delete_field(self, name: str) -> None:
        self._request("DELETE", f"/v1/fields/{name}", retry=False)

    def batches(self, name: str) -> list[dict]:
        return self._request("GET", f"/v1/fields/{name}/batches").json()["batches"]

    def snapshot(self, name: str) -> dict:
        return self._request("POST", f"/v1/fields/{name}/snapshot").json()

    # -- samples ------------------------------------------------------------
    def upload(self, name: str, values, flats: Flats | None = None, *, origins=None,
               directions=None, A=None, b=None, Q=None, r=None,
               idempotency_key: str | None = None, binary: bool = True,
               wait: bool = True) -> dict:
        """Upload one batch of samples; returns the service's report (accepted,
        rejected indices and reasons, nsamples, batch, indexed). A fresh
        Idempotency-Key is generated when none is given, so retries are safe.

        ``wait=False``: the service acknowledges once the batch is durably stored
        and its coordinates known, and triangulates it in the background
        (``report["indexed"]`` is False); see :meth:`wait_indexed`.
        """
        form, arrays = _flat_arrays(flats, dict(origins=origins, directions=directions, A=A,
                                                b=b, Q=Q, r=r))
        values = np.asarray(values, np.float64)
        if values.ndim == 1:
            values = values[:, None]
        key = idempotency_key or uuid.uuid4().hex
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

    @staticmethod
    def _encode(form, arrays, values=None) -> tuple[bytes, str]:
        if form == "rays":
            cols = [arrays["origins"], arrays["directions"]]
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
              A=None, b=None, Q=None, r=None, weights: bool = False, outside: str = "nan",
              order: str = "hilbert", binary: bool = True,
              min_position: int | None = None) -> QueryResult:
        """Interpolate the field at a batch of flats (a :class:`Flats`, or arrays by name).

        ``min_position``: read-your-writes across replicas: the ``position`` of an
        upload's report (on any replica); the server answers once it has applied
        it (503 :class:`~flatserve.service.status.ReplicaBehindError` after its wait).

        Returns the library's :class:`flatserve.QueryResult`; ``status``, ``ids``
        and ``weights`` are filled when the response carries them."""
        form, arrays = _flat_arrays(flats, dict(origins=origins, directions=directions, A=A,
                                                b=b, Q=Q, r=r))
        params = {"form": form, "outside": outside, "order": order,
                  "weights": "true" if weights else "false"}
        if min_position is not None:
            params["min_position"] = str(int(min_position))
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
        resp = self._request("POST", url, params=params, content=content,
                             headers={"Content-Type": ctype, "Accept": accept})
        if weights:
            with np.load(io.BytesIO(resp.content), allow_pickle=False) as z:
                return QueryResult(z["values"], z["inside"], z["status"], z["ids"], z["weights"])
        arr = _load_npy(resp.content)
        return QueryResult(arr[:, :-1], arr[:, -1] != 0, None)

    def query_rays(self, name: str, origins, directions, **kw) -> QueryResult:
        return self.query(name, origins=origins, directions=directions, **kw)

    def query_parametric(self, name: str, A, b, **kw) -> QueryResult:
        return self.query(name, A=A, b=b, **kw)

    def query_flats(self, name: str, Q, r, **kw) -> QueryResult:
        return self.query(name, Q=Q, r=r, **kw)

    # -- stateless math ---------------------------------------------------------
    def coordinates(self, *, k: int = 1, d: int = 3, basis: dict | None = None,
                    embed: bool = False, **flats) -> dict:
        """Coordinates of flats (``Q``/``r``, ``A``/``b`` or ``origins``/``directions``)."""
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
