"""Turn JSON flat / basis specifications into :class:`~flatserve.flats.Flats` and a
:class:`~flatserve.Basis` (no math here: everything is delegated to
:mod:`flatserve.flats` and :mod:`flatserve.basis`)."""
from __future__ import annotations

from contextlib import contextmanager

import numpy as np
from pydantic import ValidationError

from ..._validate import as_array
from ...atlas import Atlas, data_unit
from ...atlas_field import default_unit_rule
from ...contract import new_field
from ...basis import Basis
from ...errors import InvalidInputError
from ..status import BatchTooLargeError
from ...flats import FORMS, Flats, form_shapes, infer_form
from .entry import FieldSpec
from ..schemas import (ATLAS_SPECS, CenterFlat, CoveringAtlas, FieldCreate, FlatsBasis,
                      SamplesAtlas, TangentSimplexBasis)

_NAMES = tuple(n for names in FORMS.values() for n in names)


def kind_of(k: int, d: int) -> str:
    """What a field of ``k``-flats in R^d holds, in words: ``lines in R^3 (k=1, d=3)``."""
    name = {0: "points", 1: "lines", 2: "planes"}.get(k, f"{k}-flats")
    return f"{name} in R^{d} (k={k}, d={d})"


@contextmanager
def _within(prefix: str, rename: dict[str, str] | None = None):
    """Errors of the library name their argument ("Q", "directions"); here they
    get the path of the JSON member they came from ("basis.center.Q")."""
    try:
        yield
    except InvalidInputError as exc:
        arg = exc.argument
        if arg is None or arg == prefix or arg.startswith(prefix + "."):
            raise
        msg, new = str(exc), (rename or {}).get(arg, arg)
        if msg.startswith(arg + ":"):  # the message names the member as the path does
            msg = new + msg[len(arg):]
        raise type(exc)(f"{prefix}.{msg}", f"{prefix}.{new}") from None


def _arrays(obj) -> dict:
    """The flat arrays given in a JSON object or model (names of :data:`FORMS`)."""
    get = obj.get if isinstance(obj, dict) else (lambda n: getattr(obj, n, None))
    return {n: get(n) for n in _NAMES if get(n) is not None}


def flats_of(obj, k: int, d: int, prefix: str, max_rows: int | None = None) -> Flats:
    """The :class:`Flats` of an object with Q+r, A+b, origins+directions or points
    (errors name ``prefix.<array>``; more than ``max_rows`` rows is a 413)."""
    arrays = _arrays(obj)
    form = infer_form(arrays)
    if form is not None and max_rows is not None:
        n = len(arrays.get(FORMS[form][0]) or ())
        if n > max_rows:
            raise BatchTooLargeError(f"{n} flats in one request; the limit is {max_rows}")
    return Flats.from_arrays(arrays, k=k, d=d, prefix=prefix)


def flats_from(obj, k: int, d: int, prefix: str, max_rows: int | None = None,
               validate: bool = True):
    """(Q (n,d,d), r (n,d)) of an object with Q+r, A+b, origins+directions or points.

    ``validate=False`` keeps (Q, r) given directly unchecked (basis elements of a
    tangent simplex lie on the tangent plane, not on the manifold of flats)."""
    arrays = _arrays(obj)
    if not validate and infer_form(arrays) == "flats":
        Q = as_array(arrays.get("Q"), f"{prefix}.Q", ("n", d, d))
        if max_rows is not None and Q.shape[0] > max_rows:
            raise BatchTooLargeError(f"{Q.shape[0]} flats in one request; the limit is {max_rows}")
        return Q, as_array(arrays.get("r"), f"{prefix}.r", (Q.shape[0], d))
    return flats_of(obj, k, d, prefix, max_rows).quadrics()


#: The members of a centre flat by form (checked in this order), one flat each: the
#: names of :data:`FORMS` for a batch, with origins/directions/points in the singular.
_CENTER_MEMBERS = {
    "rays": ("origin", "direction"),
    "parametric": ("A", "b"),
    "flats": ("Q", "r"),
    "points": ("point",),
}


def center_flat(center: CenterFlat | None, k: int, d: int):
    """Centre (Q (d,d), r (d,)); default :meth:`Basis.default_center`."""
    if center is None:
        return Basis.default_center(k, d)
    for form, members in _CENTER_MEMBERS.items():
        if all(getattr(center, m) is None for m in members):
            continue
        if form == "rays" and k != 1:
            raise InvalidInputError("basis.center: origin/direction describe a line (k = 1)",
                                    "basis.center.origin")
        if form == "points" and k != 0:
            raise InvalidInputError(f"basis.center: point describes a point (k = 0), not a "
                                    f"{k}-flat in R^{d}", "basis.center.point")
        shapes = form_shapes(form, k, d).values()  # ("n", ...): one row here
        one = [as_array(getattr(center, m), f"basis.center.{m}", shape[1:])
               for m, shape in zip(members, shapes)]
        with _within("basis.center", dict(zip(FORMS[form], members))):
            arrays = {name: x[None] for name, x in zip(FORMS[form], one)}
            Q, r = Flats.from_arrays(arrays, k=k, d=d, form=form).quadrics()
        return Q[0], r[0]
    return Basis.default_center(k, d)


def build_basis(spec, k: int, d: int) -> Basis:
    """A :class:`flatserve.Basis` from a basis spec (None: default tangent simplex)."""
    if spec is None:
        spec = TangentSimplexBasis()
    if isinstance(spec, FlatsBasis):
        Q, r = flats_from(spec, k, d, "basis", validate=False)
        with _within("basis"):
            return Basis(Q, r, k)
    cQ, cr = center_flat(spec.center, k, d)
    with _within("basis"):
        return Basis.tangent_simplex(cQ, cr, k, scale=spec.scale, variant=spec.variant)


def oriented_of(req) -> bool:
    """A field's ``oriented`` (:class:`~..schemas.FieldCreate`): given at the top level,
    or (requests written before it) as ``basis.oriented``; both must agree. Only atlas
    fields of lines (k = 1) may be oriented (errors name where it was given)."""
    top, basis = req.oriented, req.basis
    inner = basis.oriented if isinstance(basis, ATLAS_SPECS) else None
    if top is not None and inner is not None and top != inner:
        raise InvalidInputError(
            f"oriented: the field's `oriented` ({str(top).lower()}) and `basis.oriented` "
            f"({str(inner).lower()}) disagree: give it once, at the top level", "oriented")
    oriented = bool(inner) if top is None else top
    where = "oriented" if top is not None else "basis.oriented"
    if oriented and req.k != 1:
        raise InvalidInputError(f"{where}: only lines (k = 1) have an orientation, got "
                                f"k = {req.k}", where)
    if oriented and basis is not None and not isinstance(basis, ATLAS_SPECS):
        raise InvalidInputError(
            f"oriented: a single chart (basis kind {basis.kind!r}) charts unoriented lines; "
            "an oriented field is an atlas: leave `basis` out (a covering atlas) or give "
            "{\"kind\": \"atlas\", ...}", "oriented")
    return oriented


def field_spec(req, *, max_atlas_samples: int | None = None) -> tuple[FieldSpec, Basis]:
    """What a create request (:class:`~..schemas.FieldCreate`) stores: the field's spec
    and its (chart 0's) basis, for :meth:`~.fields.FieldService.create`.

    Example: the demo's oriented covering atlas of grey rays is
    ``field_spec(FieldCreate(name="bunny", channels=1, oriented=True))``.
    """
    basis, basis_spec, atlas = build_chart_basis(req, max_atlas_samples=max_atlas_samples)
    _check_tiles(req.tiles, atlas is not None, "tiles")
    rig = rig_of(req, oriented_of(req), "rig")
    return FieldSpec(req.k, req.d, req.channels, basis_spec, req.roundtrip_tol, atlas,
                     req.copies, req.tiles, rig), basis


def rig_of(req, oriented: bool, where: str) -> dict | None:
    """A create request's ``rig`` (:class:`~..schemas.RigSpec`, its shapes already held
    to the schema) as stored, or None: the one check of a field's rig, for a create
    and for a stored definition alike (:func:`stored_spec`).

    Raises
    ------
    InvalidInputError
        Naming ``where``: a rig on a field that is not of oriented lines in R^3
        (k = 1, d = 3, ``oriented``), or of fewer than 2 channels (the colours and
        the depth channel, last).
    """
    rig = getattr(req, "rig", None)
    if rig is None:
        return None
    if (req.k, req.d) != (1, 3) or not oriented:
        kind = f"{'oriented ' if oriented else ''}{req.k}-flats in R^{req.d}"
        raise InvalidInputError(
            f"{where}: a rig (the cameras of a capture with depth) is for a light field: "
            f"oriented lines in R^3 (k = 1, d = 3, \"oriented\": true); this field holds "
            f"{kind}", where)
    if req.channels < 2:
        raise InvalidInputError(
            f"{where}: a field with a rig holds the colours and, last, the depth channel: "
            f"at least 2 channels, got {req.channels}", where)
    return rig.model_dump()


def _check_tiles(tiles, atlas: bool, where: str) -> None:
    """Tiles other than 1 are for a field of one chart (a 422 naming ``where``)."""
    if atlas and tiles != 1:
        raise InvalidInputError(
            f"{where}: {tiles} tiles are for a field of one chart (basis "
            "{\"kind\": \"tangent_simplex\"} or given flats); an atlas field's charts are "
            "its shards already (leave tiles out)", where)


#: The members of a stored definition (:meth:`~.entry.FieldSpec.to_dict`) that a create
#: request gives as they are: held to :class:`~..schemas.FieldCreate`'s constraints.
_REQUEST_MEMBERS = ("k", "d", "channels", "roundtrip_tol", "copies", "tiles", "rig")


def stored_spec(spec, Q, r, *, where: str = "spec", max_charts: int | None = None,
                basis_names: tuple[str, str] = ("basis.Q", "basis.r")
                ) -> tuple[FieldSpec, Basis]:
    """A stored definition (:meth:`~.entry.FieldSpec.to_dict`, with its basis ``Q``, ``r``)
    checked as a create checks its request, before any field is built from it: an
    export file's manifest, a field's row in the log (a replica applying its create, a
    restart restoring it). Nothing in it may be beyond what a create could have stored,
    so that no definition can make a server build something unbounded or unanswerable
    (``tiles`` 1-64 or ``"auto"``, ``copies`` 1-3, ``channels`` 1-64, ``k`` < ``d`` up
    to :data:`~..schemas.MAX_D`, ...: :class:`~..schemas.FieldCreate` itself judges them).

    Parameters
    ----------
    spec : object
        The stored definition, as read from JSON.
    Q, r : array_like
        Its basis (chart 0's for an atlas): ``(m, d, d)`` and ``(m, d)``.
    where : str
        The path errors name (``"manifest.spec"`` for an export file's).
    max_charts : int, optional
        Most charts of an atlas (none: as stored).
    basis_names : (str, str)
        The paths errors about ``Q`` and ``r`` name.

    Returns
    -------
    (FieldSpec, Basis)

    Raises
    ------
    InvalidInputError
        Naming the member (``<where>.tiles``, ``<where>.atlas``, ``basis_names``) and
        what it must be. The field is not built (its atlas is read, not charted).
    """
    if not isinstance(spec, dict):
        raise InvalidInputError(f"{where}: expected a JSON object, got {type(spec).__name__}",
                                where)
    for name in ("k", "d", "channels"):
        if name not in spec:
            raise InvalidInputError(f"{where}.{name}: missing", f"{where}.{name}")
    atlas, basis_spec = spec.get("atlas"), spec.get("basis", {})
    if atlas is not None and not isinstance(atlas, dict):
        raise InvalidInputError(f"{where}.atlas: expected an object or null", f"{where}.atlas")
    if not isinstance(basis_spec, dict):
        raise InvalidInputError(f"{where}.basis: expected an object", f"{where}.basis")
    given = {n: spec[n] for n in _REQUEST_MEMBERS if n in spec}
    if atlas is not None:
        given["oriented"] = atlas.get("oriented")
    try:
        req = FieldCreate.model_validate({"name": "stored", **given})
    except ValidationError as exc:
        raise _member_error(exc, where) from None
    with _within(where):
        oriented = oriented_of(req)  # (lines only)
    _check_tiles(req.tiles, atlas is not None, f"{where}.tiles")
    rig = rig_of(req, oriented, f"{where}.rig")
    if atlas is not None:
        _check_atlas(atlas, req.k, req.d, where, max_charts)
    names = {"Q": basis_names[0], "r": basis_names[1]}
    try:
        basis = Basis(Q, r, req.k)
        if basis.d != req.d:
            raise InvalidInputError(f"Q: flats in R^{basis.d}, the field is defined in "
                                    f"R^{req.d}", "Q")
    except InvalidInputError as exc:
        arg = names.get(exc.argument, basis_names[0])
        msg = str(exc)
        if exc.argument and msg.startswith(exc.argument + ":"):
            msg = msg[len(exc.argument) + 1:].lstrip()
        raise InvalidInputError(f"{arg}: {msg}", arg) from None
    return FieldSpec(req.k, req.d, req.channels, dict(basis_spec), req.roundtrip_tol, atlas,
                     req.copies, req.tiles, rig), basis


def _member_error(exc: ValidationError, where: str) -> InvalidInputError:
    """The first member a :class:`~..schemas.FieldCreate` refused, as one 422 naming it
    (the messages of each alternative of a union together) and the value given."""
    errs = exc.errors()
    loc = errs[0]["loc"][:1]
    path = ".".join([where, *map(str, loc)])
    msgs = dict.fromkeys(e["msg"].removeprefix("Value error, ") for e in errs
                         if e["loc"][:1] == loc)
    got = f", got {errs[0]['input']!r}"[:80] if loc else ""
    return InvalidInputError(f"{path}: {' or '.join(msgs)}{got}", path)


def _check_atlas(atlas: dict, k: int, d: int, where: str, max_charts: int | None) -> None:
    """A stored atlas (:meth:`flatserve.atlas.Atlas.to_dict`) reads as an atlas of
    ``k``-flats in R^d (at most ``max_charts`` charts), without being charted."""
    path = f"{where}.atlas"
    scales = atlas.get("scales")
    n = len(scales) if isinstance(scales, list) else None
    if n is None or n < 1:
        raise InvalidInputError(f"{path}.scales: expected a list of one scale per chart",
                                f"{path}.scales")
    if max_charts is not None and n > max_charts:
        raise InvalidInputError(f"{path}: {n} charts; at most {max_charts}", path)
    ak, ad = atlas.get("k"), atlas.get("d")
    if (ak, ad) != (k, d) or isinstance(ak, bool) or isinstance(ad, bool):
        # (before it is read: its charts' sizes follow its own k and d)
        raise InvalidInputError(f"{path}: charts {ak}-flats in R^{ad}, the field is defined "
                                f"for {k}-flats in R^{d}", path)
    try:
        Atlas.from_dict(atlas)
    except Exception as exc:  # a damaged or foreign atlas: say what failed
        arg = getattr(exc, "argument", None)
        where_ = f"{path}.{arg}" if arg else path
        raise InvalidInputError(f"{path}: cannot be read: {type(exc).__name__}: {exc}"[:300],
                                where_) from None


def build_chart_basis(req, *, max_atlas_samples: int | None = None
                      ) -> tuple[Basis, dict, dict | None]:
    """A field's basis from its create request (:class:`~..schemas.FieldCreate`).

    Returns
    -------
    (Basis, dict, dict or None)
        One chart: its basis, its spec (as stored and described), None. An atlas
        (the default when ``basis`` is left out): chart 0's basis, the atlas spec
        (the sample flats of ``samples`` replaced by their count), and the atlas
        (:meth:`flatserve.atlas.Atlas.to_dict`, stored with the field).
    """
    k, d = req.k, req.d
    spec = CoveringAtlas() if req.basis is None else req.basis
    oriented = oriented_of(req)
    given = getattr(req, "unit", None)
    if given is not None and not isinstance(spec, ATLAS_SPECS):
        raise InvalidInputError(
            f"unit: a single chart (basis kind {spec.kind!r}) has its own `scale`; `unit` is "
            "an atlas's: leave `basis` out (a covering atlas) or give {\"kind\": \"atlas\", ...}",
            "unit")
    if isinstance(spec, ATLAS_SPECS):
        atlas = build_atlas(spec, k, d, oriented=oriented, max_atlas_samples=max_atlas_samples,
                            unit=atlas_unit(given, k, d))
        return atlas.bases[0], _atlas_spec_dict(spec), atlas.to_dict()
    return build_basis(spec, k, d).require_full(), spec_dict(spec), None


def atlas_unit(given: float | str | None, k: int, d: int) -> float | str | None:
    """The library's ``Atlas(unit=...)`` for a create request's ``unit``: a length as
    given; left out, :func:`flatserve.atlas_field.default_unit_rule` of the kind
    (``"fit"`` up to R^4, but for points); ``"data"``: None
    (:func:`flatserve.atlas.data_unit`)."""
    if given is None:
        given = default_unit_rule(k, d)
    return None if given == "data" else given


#: Most centres of an atlas given explicitly (``atlas: "centers"``).
MAX_ATLAS_CENTERS = 1024


def build_atlas(spec, k: int, d: int, *, oriented: bool = False,
                max_atlas_samples: int | None = None, unit: float | str | None = None) -> Atlas:
    """The :class:`flatserve.atlas.Atlas` of an atlas spec (errors name ``basis.<member>``).

    ``covering``: :meth:`Atlas.covering`. ``samples``: :meth:`Atlas.for_samples` of the
    given flats (more than ``max_atlas_samples`` is a 413), refused (422) unless its
    charts hold every one of them. ``centers``: :meth:`Atlas.from_centers`, refused
    (422) unless every orientation lies within a chart's trusted radius and every chart
    round-trips its domain. ``unit``: the charts' unit of length (the field's `unit`,
    stored in the atlas: a restored field keeps it); None or ``"fit"``: chosen from the
    field's first batch (:func:`flatserve.atlas_field.choose_unit`; the upload room
    stores it with the batch)."""
    if isinstance(spec, CoveringAtlas):
        with _within("basis"):
            return Atlas.covering(k, d, oriented=oriented, unit=unit, inner=spec.inner,
                                  trusted=spec.trusted, reach=spec.reach,
                                  dense_reach=spec.dense_reach, dense_after=spec.dense_after,
                                  seam_spacing=spec.seam_spacing,
                                  isometric=spec.isometric, relative=spec.relative)
    if isinstance(spec, SamplesAtlas):
        _check_rows(spec.samples, "basis.samples", max_atlas_samples,
                    "FLATSERVE_MAX_ATLAS_SAMPLES")
        flats = flats_of(spec.samples, k, d, "basis.samples")
        with _within("basis", {"flats": "samples", **{n: f"samples.{n}" for n in _NAMES}}):
            atlas = Atlas.for_samples(flats, oriented=oriented, radius=spec.radius,
                                      fraction=spec.fraction, unit=unit)
        _require_charted(atlas, flats)
        return atlas
    _check_rows(spec.centers, "basis.centers", MAX_ATLAS_CENTERS, None)
    centers = flats_of(spec.centers, k, d, "basis.centers")
    scale = spec.scale
    if isinstance(scale, list) and len(scale) != centers.n:
        raise InvalidInputError(f"basis.scale: expected one scale or {centers.n} (one per "
                                f"centre), got {len(scale)}", "basis.scale")
    with _within("basis", {"scales": "scale"}):
        return Atlas.from_centers(centers, scale, oriented=oriented, unit=unit)


def _check_rows(model, where: str, limit: int | None, setting: str | None) -> None:
    """A 413 (``setting`` given) or 422 naming ``where`` for more than ``limit`` flats."""
    arrays = _arrays(model)
    form = infer_form(arrays)
    n = 0 if form is None else len(arrays.get(FORMS[form][0]) or ())
    if limit is not None and n > limit:
        if setting is not None:
            raise BatchTooLargeError(f"{where}: {n} flats; the limit is {limit} ({setting})")
        raise InvalidInputError(f"{where}: {n} flats; at most {limit}", where)


def _require_charted(atlas: Atlas, flats: Flats) -> None:
    """Refuse (422, ``basis.samples``) a data-driven atlas that does not chart every
    flat it was built for: which rows, and why the first is not."""
    zeros = np.zeros(flats.n)
    if atlas.unit_from_data:  # charted in the geometry's unit (no fit on made-up values)
        atlas = atlas.with_unit(data_unit(flats, zeros))
    prepared = new_field(1, atlas=atlas).prepare(flats, zeros)
    bad = prepared.rejected
    if bad.size:
        rows = ", ".join(str(i) for i in bad[:5].tolist()) + (", ..." if bad.size > 5 else "")
        raise InvalidInputError(
            f"basis.samples: the atlas built for these {flats.n} flats does not chart "
            f"{bad.size} of them (rows {rows}); row {int(bad[0])}: {prepared.reasons[0]}",
            "basis.samples")


def _atlas_spec_dict(spec) -> dict:
    """An atlas spec as stored and described: ``oriented`` is the field's (top level);
    the flats of ``samples`` are replaced by their number and form."""
    out = spec.model_dump(exclude_none=True, exclude={"oriented", "samples"})
    if isinstance(spec, SamplesAtlas):
        arrays = _arrays(spec.samples)
        form = infer_form(arrays)
        out["samples"] = {"form": form, "n": len(arrays[FORMS[form][0]])}
    return out


def spec_dict(spec) -> dict:
    """A one-chart basis spec as stored and described."""
    return spec.model_dump(exclude_none=True)
