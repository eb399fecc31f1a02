"""The transfer room: export a field as one file, import it on another deployment.

An export is an ``.npz`` (a zip of ``.npy`` members, ``numpy.load`` reads it with
``allow_pickle=False``) of everything that defines the field and its samples:

* ``manifest``: uint8, the UTF-8 bytes of a JSON object: ``format`` (1), ``field``
  (its name), ``export_id``, ``spec`` (the stored definition:
  :class:`~.entry.FieldSpec`, with an atlas's centres and scales), and ``batches``:
  per stored batch in log order its ``seq``, ``form`` and ``rows``;
* ``basis_Q``, ``basis_r``: chart 0's basis flats as stored;
* per form of the batches, their arrays in batch order, concatenated:
  ``rays_origins``, ``rays_directions``, ``parametric_A``, ``parametric_b``,
  ``flats_Q``, ``flats_r``; and ``values``, the values of every batch.

An import creates the field from the stored definition (no create request: an
atlas is taken as it was built, not built again) and stores the batches in their
order through the upload room, each under the Idempotency-Key
``import-<export_id>.<seq>``: the field answers bit for bit as the exported one,
and an import repeated after a failure stores only the batches still missing (an
existing field is taken when its definition is the file's). The import rebuilds
the triangulation from the batches (the cost of a restore without a snapshot).

The whole file is checked before anything is stored (:func:`read_export`): the
manifest's definition as a create checks its request (:func:`.specs.stored_spec`:
the same limits, ``tiles`` 1-64, ``copies`` 1-3, ...), its ``format`` (exactly the
integer 1), ``export_id`` (a short token), at most ``max_import_batches`` batches
of their own ``seq`` and at most ``max_batch_rows`` rows, then every batch as its
upload will check it, one at a time (a batch decoded at a time beside the file's
arrays; the store pass decodes each again), and the cost of all its batches not yet
stored at once as an upload's (:func:`.uploads.check_cost`, ``max_simplices``): a
refused file leaves no field. The batches are then stored without a cost check of
their own, which could refuse one part-way with an estimate measured meanwhile;
instead their rows are reserved (:meth:`.entry.FieldEntry.reserve`): an upload
meanwhile counts them as pending, and a second import into the same field waits
for the first (this process's imports; replicas judge each against what they hold).
"""
from __future__ import annotations

import io
import json
import re
import threading
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from dataclasses import field as dc_field

import numpy as np

from ..._validate import as_array
from ...basis import Basis
from ...contract import SampledField
from ...errors import InvalidInputError
from ...flats import FORMS, Flats
from . import specs
from ..log.backend import LogBackend
from ..binary import load_npz
from .catalogue import FieldCatalogue
from .entry import FieldEntry, FieldSpec
from .fields import FieldService
from ..reports import ImportResult
from ..settings import FIELD_NAME_PATTERN, Settings
from .specs import MAX_ATLAS_CENTERS
from ..status import (BatchTooLargeError, FieldExistsError, FieldNotFoundError,
                     LimitExceededError)
from .uploads import UploadService, check_cost

__all__ = ["EXPORT_FORMAT", "ExportPlan", "TransferService", "read_export"]

#: The version of the export file's layout
EXPORT_FORMAT = 1
MANIFEST = "manifest"
#: Longest ``export_id``: it goes into the Idempotency-Keys of the imported batches
#: (``import-<export_id>.<seq>``), so it is a short token of letters, digits, ``_``, ``-``
MAX_EXPORT_ID = 128
EXPORT_ID = re.compile(rf"[A-Za-z0-9_-]{{1,{MAX_EXPORT_ID}}}")
#: Deepest nesting of a manifest's JSON (an export's is at most 6 levels deep): deeper
#: is a 422, whatever the depth at which the parser's RecursionError (about 1000
#: levels, less on a deeper stack) or a later step's recursion would fail
MAX_MANIFEST_DEPTH = 32


def _member(form: str, name: str) -> str:
    return f"{form}_{name}"


@dataclass
class TransferService:
    """Export and import of fields (see the module doc).

    Parameters
    ----------
    settings : Settings
    storage : LogBackend
        The stored batches and definitions.
    catalogue : FieldCatalogue
    fields : FieldService
        Creates the imported field.
    uploads : UploadService
        Stores the imported batches (durably, through the log, idempotently).
    """

    settings: Settings
    storage: LogBackend
    catalogue: FieldCatalogue
    fields: FieldService
    uploads: UploadService
    _import_locks: dict = dc_field(default_factory=dict, init=False, repr=False)
    _locks_lock: threading.Lock = dc_field(default_factory=threading.Lock, init=False,
                                           repr=False)

    def export(self, e: FieldEntry) -> bytes:
        """The export file of field ``e`` (its stored batches at this moment)."""
        rows = self.storage.batches(e.id)
        parts: dict[str, list[np.ndarray]] = {}
        batches = []
        for b in rows:
            arrays = self.storage.batch_arrays(e.id, b.seq)
            for name in FORMS[b.form]:
                parts.setdefault(_member(b.form, name), []).append(np.asarray(arrays[name]))
            parts.setdefault("values", []).append(np.asarray(arrays["values"]))
            batches.append({"seq": b.seq, "form": b.form, "rows": b.nrows})
        spec, basis = _settled(e), e.basis
        manifest = {"format": EXPORT_FORMAT, "field": e.name, "export_id": uuid.uuid4().hex,
                    "spec": spec, "batches": batches}
        out = {MANIFEST: np.frombuffer(json.dumps(manifest).encode(), np.uint8),
               "basis_Q": basis.Q, "basis_r": basis.r}
        for name, arrs in parts.items():
            out[name] = np.concatenate(arrs)
        if "values" not in out:
            out["values"] = np.zeros((0, e.spec.channels))
        buf = io.BytesIO()
        np.savez(buf, **out)
        return buf.getvalue()

    def import_field(self, name: str, body: bytes) -> ImportResult:
        """Create field ``name`` from an export file and store its batches.

        The whole file is checked before anything is stored (:func:`read_export`:
        the definition as a create's, every batch as an upload's, against this
        server's limits); a file refused leaves no field. Then the batches are stored
        one at a time (a batch decoded at a time), each under its Idempotency-Key.

        Raises
        ------
        InvalidInputError
            Not an export file, or one whose parts disagree or hold a batch an upload
            refuses (422, naming the part).
        LimitExceededError
            More batches than ``max_import_batches``, or a batch of more rows than
            ``max_batch_rows`` (413).
        CostLimitError, CostPendingError
            The batches not yet stored would make the field larger than
            ``max_simplices`` cells (413; 429 when the field's samples waiting for
            their insert make the difference): :func:`.uploads.check_cost`.
        FieldExistsError
            ``name`` exists with another definition (409).
        """
        plan = read_export(body, self.settings)
        with self._importing(name):  # imports into one field judged one after another
            e = self._existing(name, plan.spec, plan.basis)
            self._check_cost(name, plan, e)
            if e is None:
                e = self._field(name, plan.spec, plan.basis)
            with e.upload_lock:  # judged again with the uploads stopped, and reserved
                left = self._check_cost(name, plan, e)
                e.reserve(left)
            accepted = replayed = 0
            out = None
            try:
                for b, flats, values in plan.each():
                    out = self.uploads.upload(e, flats, values, plan.key(b), wait=True,
                                              cost_checked=True)
                    accepted += out.accepted if not out.replayed else 0
                    replayed += bool(out.replayed)
                    if not out.replayed:
                        e.reserve(-len(flats))
                        left -= len(flats)
            finally:
                e.reserve(-left)
        return ImportResult(name=name, source=plan.source, batches=len(plan.batches),
                            replayed_batches=replayed, accepted=accepted,
                            nsamples=e.field.nsamples if e.field is not None else 0,
                            position=out.position if out is not None else 0)

    @contextmanager
    def _importing(self, name: str):
        """Hold field ``name`` for one import at a time in this process: the second
        is judged by the cost guard once the first's batches are stored."""
        with self._locks_lock:  # name -> [its lock, the imports holding or awaiting it]
            held = self._import_locks.setdefault(name, [threading.Lock(), 0])
            held[1] += 1
        try:
            with held[0]:
                yield
        finally:
            with self._locks_lock:
                held[1] -= 1
                if not held[1]:
                    del self._import_locks[name]

    def _check_cost(self, name: str, plan: "ExportPlan", e: FieldEntry | None) -> int:
        """The cost guard of the upload (:func:`.uploads.check_cost`) for the file's
        batches not yet stored in field ``e`` (all of them for a new field, ``None``),
        at once, before any is stored: their rows."""
        stored = set() if e is None else {b.idem_key for b in self.storage.batches(e.id)}
        new = [(b["rows"], c) for b, c in zip(plan.batches, plan.copies)
               if plan.key(b) not in stored]
        rows = sum(n for n, _ in new)
        if not rows:
            return 0
        copies = sum(n * c for n, c in new) / rows
        if e is None:
            check_cost(name, plan.field, (0, 0), 0, rows, copies, self.settings.max_simplices,
                       what="this import")
        else:
            pending = e.pending_counts()[1] + e.reserved
            check_cost(name, e.field, e.complete_size, pending, rows, copies,
                       self.settings.max_simplices, what="this import")
        return rows

    def _existing(self, name: str, spec: FieldSpec, basis: Basis) -> FieldEntry | None:
        """The existing field ``name`` if its definition is the file's; None if there
        is none.

        Raises
        ------
        FieldExistsError
            It exists with another definition (409).
        NotReadyError, StorageError
            It is loading, or failed (503).
        """
        try:
            e = self.catalogue.get(name)
        except FieldNotFoundError:
            return None
        same = (e.spec.to_dict() == json.loads(json.dumps(spec.to_dict()))
                and np.array_equal(e.basis.Q, basis.Q) and np.array_equal(e.basis.r, basis.r))
        if not same:
            raise FieldExistsError(f"field {name!r} exists with another definition than "
                                   "the file's: import under another name, or delete it "
                                   "first")
        return e

    def _field(self, name: str, spec: FieldSpec, basis: Basis) -> FieldEntry:
        """The new field, or the existing one of that name if its definition is the
        file's (created meanwhile)."""
        try:
            return self.fields.create(name, spec, basis)
        except FieldExistsError:
            e = self._existing(name, spec, basis)
            if e is None:
                raise FieldExistsError(f"field {name!r} exists (or the field limit is "
                                       "reached)") from None
            return e


@dataclass
class ExportPlan:
    """An export file read and checked whole (:func:`read_export`): what an import
    stores, batch by batch (:meth:`each`)."""

    #: the name of the exported field and the export's id (the key of its batches)
    source: str
    export_id: str
    spec: FieldSpec
    basis: Basis
    #: the manifest's batches in order: ``{"seq", "form", "rows"}``
    batches: list[dict]
    #: the file's arrays by member name
    arrays: dict[str, np.ndarray]
    #: an empty field of the definition (built once, to check the batches)
    field: SampledField
    #: per batch, the charts holding each of its rows on average (the field's ``copies``)
    copies: list[float]

    def key(self, batch: dict) -> str:
        """The Idempotency-Key under which ``batch`` (of :attr:`batches`) is stored."""
        return f"import-{self.export_id}.{batch['seq']}"

    def each(self) -> Iterator[tuple[dict, Flats, np.ndarray]]:
        """``(batch, flats, values)`` of each batch in order, built when reached (a
        batch at a time in memory beside the file's arrays).

        Raises
        ------
        InvalidInputError
            A batch's flats or values are not valid (naming the member, the batch and
            its rows in the file).
        """
        offsets = {form: 0 for form in FORMS}
        voff = 0
        for i, b in enumerate(self.batches):
            form, n = b["form"], b["rows"]
            at = offsets[form]
            arrays = {k: self.arrays[_member(form, k)][at:at + n] for k in FORMS[form]}
            values = self.arrays["values"][voff:voff + n]
            where = (f"batch {i} (seq {b['seq']}: rows {at}-{at + n - 1} of the {form} "
                     f"arrays, {voff}-{voff + n - 1} of values)")
            offsets[form] += n
            voff += n
            with _in_batch(where, form):
                flats = Flats.from_arrays(arrays, k=self.spec.k, d=self.spec.d, form=form,
                                          min_rows=1)
                values = as_array(values, "values", (n, self.spec.channels))
            yield b, flats, np.ascontiguousarray(values)


@contextmanager
def _in_batch(where: str, form: str):
    """An error about a batch's array (``directions``, ``values``) as one naming the
    file's member (``rays_directions``) and the batch."""
    try:
        yield
    except InvalidInputError as exc:
        arg = exc.argument or "body"
        member = _member(form, arg) if arg in FORMS[form] else arg
        msg = str(exc)
        if msg.startswith(arg + ":"):
            msg = msg[len(arg) + 1:].lstrip()
        raise type(exc)(f"{member}: {where}: {msg}"[:500], member) from None


def _settled(e: FieldEntry) -> dict:
    """The stored definition of ``e`` as exported: a unit of length it chose from its
    first batch is written in (the atlas in that unit, its warps calibrated again on
    import), so the imported field charts its batches in it from the start (the basis
    exported beside it stays the one stored at its creation, chart 0's as described)."""
    spec = e.spec.to_dict()
    f, at = e.field, (spec.get("atlas") or None)
    if at is None or not at.get("unit_from_data") or f is None or f.unit_pending:
        return spec
    rule = at.get("unit_rule", "data")
    at = {k: v for k, v in at.items() if k not in ("unit_from_data", "unit_rule", "warps")}
    at["unit"] = f.unit
    at["info"] = {**at.get("info", {}), "unit_from": rule}
    return {**spec, "atlas": at}


def _bad(msg: str) -> InvalidInputError:
    return InvalidInputError(f"body: {msg}", "body")


def _depth(obj, limit: int) -> int:
    """How deeply JSON value ``obj`` nests (``[]`` is 1, a scalar 0), counted
    without recursion up to ``limit + 1``."""
    deepest, todo = 0, [(obj, 1)]
    while todo and deepest <= limit:
        x, d = todo.pop()
        if isinstance(x, (dict, list)):
            deepest = max(deepest, d)
            todo.extend((v, d + 1) for v in (x.values() if isinstance(x, dict) else x))
    return deepest


def _manifest(raw: bytes):
    """The manifest's JSON value; 422 at ``["body", "manifest"]`` when its bytes are
    not JSON or nest deeper than :data:`MAX_MANIFEST_DEPTH`."""
    too_deep = InvalidInputError(
        f"manifest: not an export's manifest: JSON nested more than {MAX_MANIFEST_DEPTH} "
        "levels deep", MANIFEST)
    try:
        manifest = json.loads(raw)
    except RecursionError:
        raise too_deep from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise InvalidInputError(f"manifest: not JSON: {exc}"[:300], MANIFEST) from None
    if _depth(manifest, MAX_MANIFEST_DEPTH) > MAX_MANIFEST_DEPTH:
        raise too_deep
    return manifest


def read_export(body: bytes, settings: Settings) -> ExportPlan:
    """An export file read and checked whole before anything is stored: the manifest
    (``format`` exactly the integer :data:`EXPORT_FORMAT`, ``export_id`` a short token,
    at most ``max_import_batches`` batches, each ``{seq, form, rows}`` with a ``seq``
    of its own and at most ``max_batch_rows`` rows), the definition as a create
    checks its request (:func:`.specs.stored_spec`) and built once, the members' rows
    against the manifest, then every batch as an upload checks it (the field's
    ``prepare``, which validates without charting), a batch at a time.

    Raises
    ------
    InvalidInputError
        422 naming the part (``manifest.<member>``, a member of the file).
    LimitExceededError
        413: more batches than ``max_import_batches``, or a batch of more rows than
        ``max_batch_rows``.
    """
    arrays = load_npz(body)
    if MANIFEST not in arrays:
        raise _bad("not a flatserve export (no `manifest` member); make one with "
                   "GET /v1/fields/{name}/export")
    manifest = _manifest(bytes(np.asarray(arrays[MANIFEST], np.uint8)))
    if not isinstance(manifest, dict):
        raise InvalidInputError(f"manifest: expected a JSON object, got "
                                f"{type(manifest).__name__}", MANIFEST)
    fmt = manifest.get("format")
    if type(fmt) is not int or fmt != EXPORT_FORMAT:  # (true is an int to Python)
        raise InvalidInputError(f"manifest.format: format {fmt!r}"[:200] + "; this server "
                                f"reads format {EXPORT_FORMAT}", "manifest.format")
    source, export_id = manifest.get("field"), manifest.get("export_id")
    if not (isinstance(source, str) and re.fullmatch(FIELD_NAME_PATTERN, source)):
        raise InvalidInputError(f"manifest.field: expected the exported field's name, got "
                                f"{source!r}"[:200], "manifest.field")
    if not (isinstance(export_id, str) and EXPORT_ID.fullmatch(export_id)):
        raise InvalidInputError(f"manifest.export_id: expected 1-{MAX_EXPORT_ID} letters, "
                                f"digits, '_' or '-', got {export_id!r}"[:200],
                                "manifest.export_id")
    listed = _listed(manifest.get("batches"), settings)
    spec, basis = specs.stored_spec(
        manifest.get("spec"), arrays.get("basis_Q"), arrays.get("basis_r"),
        where="manifest.spec", basis_names=("basis_Q", "basis_r"),
        max_charts=max(MAX_ATLAS_CENTERS, settings.max_atlas_samples))
    try:
        probe = spec.new_field(basis)  # the definition builds a field (an atlas from its centres)
    except InvalidInputError:
        raise
    except Exception as exc:  # a damaged or foreign definition: say what failed
        raise InvalidInputError(f"manifest.spec: the field's definition cannot be built: "
                                f"{type(exc).__name__}: {exc}"[:300], "manifest.spec") from None
    rows = {form: 0 for form in FORMS}
    for b in listed:
        rows[b["form"]] += b["rows"]
    for form, n in rows.items():
        for name in FORMS[form]:
            member = _member(form, name)
            have = arrays[member].shape[0] if member in arrays else 0
            if have != n:
                raise _bad(f"{member}: {have} rows, the manifest's {form} batches have {n}")
    total = sum(rows.values())
    vals = arrays.get("values")
    if vals is None or vals.ndim != 2 or vals.shape != (total, spec.channels):
        raise _bad(f"values: expected ({total}, {spec.channels}), got "
                   f"{None if vals is None else vals.shape}")
    plan = ExportPlan(source, export_id, spec, basis, listed, arrays, probe, [])
    for i, (b, flats, values) in enumerate(plan.each()):  # as its upload will check it
        with _in_batch(f"batch {i} (seq {b['seq']})", b["form"]):
            probe.prepare(flats, values, defer=True)
            plan.copies.append(probe.copies(flats))
    return plan


def _listed(listed, settings: Settings) -> list[dict]:
    """The manifest's ``batches`` checked: a list of at most ``max_import_batches``
    ``{seq, form, rows}`` (``seq`` >= 1 of its own, ``1 <= rows <= max_batch_rows``)."""
    if not isinstance(listed, list):
        raise InvalidInputError("manifest.batches: expected a list of the stored batches",
                                "manifest.batches")
    if len(listed) > settings.max_import_batches:
        raise LimitExceededError(
            f"manifest.batches: {len(listed):,} batches; an import stores at most "
            f"{settings.max_import_batches:,} (FLATSERVE_MAX_IMPORT_BATCHES)")
    seen: set[int] = set()
    for i, b in enumerate(listed):
        where = f"manifest.batches.{i}"
        if not (isinstance(b, dict) and b.get("form") in FORMS
                and all(type(b.get(n)) is int and b[n] >= 1 for n in ("seq", "rows"))):
            raise InvalidInputError(f"{where}: expected {{seq >= 1, form (one of "
                                    f"{', '.join(FORMS)}), rows >= 1}}, got {b!r}"[:300], where)
        if b["rows"] > settings.max_batch_rows:
            raise BatchTooLargeError(
                f"{where}: {b['rows']:,} rows in one batch; the limit is "
                f"{settings.max_batch_rows:,} (FLATSERVE_MAX_BATCH_ROWS)")
        if b["seq"] in seen:
            raise InvalidInputError(f"{where}: seq {b['seq']} is listed twice", where)
        seen.add(b["seq"])
    return [{"seq": b["seq"], "form": b["form"], "rows": b["rows"]} for b in listed]
