"""Turn JSON flat / basis specifications into :class:`~flatserve.flats.Flats` and a
:class:`~flatserve.Basis` (no math here: everything is delegated to
:mod:`flatserve.flats` and :mod:`flatserve.basis`)."""
from __future__ import annotations

from contextlib import contextmanager

from .._validate import as_array
from ..atlas import Atlas
from ..basis import Basis
from ..errors import BatchTooLargeError, InvalidInputError
from ..flats import FORMS, Flats, form_shapes, infer_form
from .schemas import AtlasBasis, CenterFlat, FlatsBasis, TangentSimplexBasis

_NAMES = tuple(n for names in FORMS.values() for n in names)


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
        arg = (rename or {}).get(arg, arg)
        raise type(exc)(f"{prefix}.{exc}", f"{prefix}.{arg}") from None


def _arrays(obj) -> dict:
    """The flat arrays given in a JSON object or model (names of :data:`FORMS`)."""
    get = obj.get if isinstance(obj, dict) else (lambda n: getattr(obj, n, None))
    return {n: get(n) for n in _NAMES if get(n) is not None}


def flats_of(obj, k: int, d: int, prefix: str, max_rows: int | None = None) -> Flats:
    """The :class:`Flats` of an object with Q+r, A+b or origins+directions
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
    """(Q (n,d,d), r (n,d)) of an object with Q+r, A+b or origins+directions.

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
#: names of :data:`FORMS` for a batch, with origins/directions in the singular.
_CENTER_MEMBERS = {
    "rays": ("origin", "direction"),
    "parametric": ("A", "b"),
    "flats": ("Q", "r"),
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


def build_chart_basis(spec, k: int, d: int) -> tuple[Basis, dict | None]:
    """A field's basis from its spec: ``(basis, None)`` for one chart, or for an
    atlas (:class:`AtlasBasis`) chart 0's basis and the atlas
    (:meth:`flatserve.atlas.Atlas.to_dict`, stored with the field)."""
    if isinstance(spec, AtlasBasis):
        atlas = build_atlas(spec, k, d)
        return atlas.bases[0], atlas.to_dict()
    return build_basis(spec, k, d).require_full(), None


def build_atlas(spec: AtlasBasis, k: int, d: int) -> Atlas:
    """The :class:`flatserve.atlas.Atlas` of an atlas spec (errors name ``basis.<member>``)."""
    with _within("basis"):
        return Atlas.covering(k, d, oriented=spec.oriented)


def spec_dict(spec) -> dict:
    if spec is None:
        spec = TangentSimplexBasis()
    return spec.model_dump(exclude_none=True)
