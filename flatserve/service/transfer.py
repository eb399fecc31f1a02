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
"""
from __future__ import annotations

import io
import json
import uuid
from dataclasses import dataclass

import numpy as np

from ..basis import Basis
from ..errors import InvalidInputError
from ..flats import FORMS, Flats
from .backend import LogBackend
from .binary import load_npz
from .catalogue import FieldCatalogue
from .entry import FieldEntry, FieldSpec
from .fields import FieldService
from .schemas import MAX_D, ImportResult
from .settings import Settings
from .specs import MAX_ATLAS_CENTERS
from .status import FieldExistsError, FieldNotFoundError
from .uploads import UploadService

__all__ = ["EXPORT_FORMAT", "TransferService"]

#: The version of the export file's layout
EXPORT_FORMAT = 1
MANIFEST = "manifest"
#: Most stored batches one export may list
MAX_EXPORT_BATCHES = 1_000_000
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

        Raises
        ------
        InvalidInputError
            Not an export file, or one whose parts disagree (422, naming the part).
        FieldExistsError
            ``name`` exists with another definition (409).
        """
        manifest, spec, basis, batches = _read(body)
        e = self._field(name, spec, basis)
        offsets = {form: 0 for form in FORMS}
        voff = 0
        accepted = replayed = 0
        out = None
        for b in batches:
            form, n = b["form"], b["rows"]
            arrays = {k: batches.arrays[_member(form, k)][offsets[form]:offsets[form] + n]
                      for k in FORMS[form]}
            values = batches.arrays["values"][voff:voff + n]
            offsets[form] += n
            voff += n
            flats = Flats.from_arrays(arrays, k=spec.k, d=spec.d, form=form, min_rows=1)
            out = self.uploads.upload(e, flats, np.ascontiguousarray(values),
                                      f"import-{manifest['export_id']}.{b['seq']}", wait=True)
            accepted += out.accepted if not out.replayed else 0
            replayed += bool(out.replayed)
        return ImportResult(name=name, source=manifest["field"], batches=len(batches),
                            replayed_batches=replayed, accepted=accepted,
                            nsamples=e.field.nsamples if e.field is not None else 0,
                            position=out.position if out is not None else 0)

    def _field(self, name: str, spec: FieldSpec, basis: Basis) -> FieldEntry:
        """The new field, or the existing one of that name if its definition is the file's."""
        try:
            return self.fields.create(name, spec, basis)
        except FieldExistsError:
            try:
                e = self.catalogue.get(name)
            except FieldNotFoundError:
                raise FieldExistsError(f"field {name!r} exists (or the field limit is "
                                       "reached)") from None
            same = (e.spec.to_dict() == json.loads(json.dumps(spec.to_dict()))
                    and np.array_equal(e.basis.Q, basis.Q) and np.array_equal(e.basis.r, basis.r))
            if not same:
                raise FieldExistsError(f"field {name!r} exists with another definition than "
                                       "the file's: import under another name, or delete it "
                                       "first") from None
            return e


class _Batches(list):
    """The manifest's batches, with the file's arrays by member name."""

    arrays: dict[str, np.ndarray]


def _settled(e: FieldEntry) -> dict:
    """The stored definition of ``e`` as exported: a unit of length it chose from its
    first batch is written in (the atlas in that unit, its warps calibrated again on
    import), so the imported field charts its batches in it from the start (the basis
    exported beside it stays the one stored at its creation, chart 0's as described)."""
    spec = e.spec.to_dict()
    f, at = e.field, (spec.get("atlas") or None)
    if at is None or not at.get("unit_from_data") or getattr(f, "unit_pending", True):
        return spec
    rule = at.get("unit_rule", "data")
    at = {k: v for k, v in at.items() if k not in ("unit_from_data", "unit_rule", "warps")}
    at["unit"] = f.atlas.unit
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


def _read(body: bytes) -> tuple[dict, FieldSpec, Basis, _Batches]:
    """The manifest, definition, basis and batches of an export file, every part
    checked against the others before anything is stored."""
    arrays = load_npz(body)
    if MANIFEST not in arrays:
        raise _bad("not a flatserve export (no `manifest` member); make one with "
                   "GET /v1/fields/{name}/export")
    manifest = _manifest(bytes(np.asarray(arrays[MANIFEST], np.uint8)))
    if not isinstance(manifest, dict) or manifest.get("format") != EXPORT_FORMAT:
        raise _bad(f"manifest: format {manifest.get('format') if isinstance(manifest, dict) else None!r}"
                   f"; this server reads format {EXPORT_FORMAT}")
    try:
        spec = FieldSpec.from_dict(manifest["spec"])
        if not (0 <= spec.k < spec.d <= MAX_D and 1 <= spec.channels <= 64):
            raise ValueError(f"k={spec.k}, d={spec.d}, channels={spec.channels} out of range")
        if spec.atlas is not None and len(spec.atlas.get("scales", ())) > MAX_ATLAS_CENTERS:
            raise ValueError(f"more than {MAX_ATLAS_CENTERS} charts")
        Q = np.asarray(arrays["basis_Q"], np.float64)
        r = np.asarray(arrays["basis_r"], np.float64)
        basis = Basis(Q, r, spec.k)
        spec.new_field(basis)  # the definition builds a field (an atlas from its centres)
    except InvalidInputError:
        raise
    except Exception as exc:  # a damaged or foreign definition: say what failed
        raise _bad(f"manifest: the field's definition cannot be read: "
                   f"{type(exc).__name__}: {exc}") from None
    listed = manifest.get("batches")
    if not isinstance(listed, list) or len(listed) > MAX_EXPORT_BATCHES:
        raise _bad("manifest: `batches` must be a list of the stored batches")
    batches = _Batches()
    rows = {form: 0 for form in FORMS}
    for i, b in enumerate(listed):
        if not (isinstance(b, dict) and b.get("form") in FORMS and isinstance(b.get("rows"), int)
                and b["rows"] >= 1 and isinstance(b.get("seq"), int)):
            raise _bad(f"manifest: batch {i}: expected {{seq, form, rows >= 1}}, got {b!r}"[:300])
        rows[b["form"]] += b["rows"]
        batches.append(b)
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
    batches.arrays = arrays
    return manifest, spec, basis, batches
