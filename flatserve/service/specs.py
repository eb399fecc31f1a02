"""Turn JSON flat / basis specifications into :class:`~flatserve.flats.Flats` and a
:class:`~flatserve.Basis` (no math here: everything is delegated to
:mod:`flatserve.flats` and :mod:`flatserve.basis`)."""
from __future__ import annotations

from contextlib import contextmanager

from .._validate import as_array
from ..basis import Basis
from ..errors import InvalidInputError
from ..flats import FORMS, Flats, infer_form
from .errors import BatchTooLargeError
from .schemas import CenterFlat, FlatsBasis, TangentSimplexBasis

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


def center_flat(center: CenterFlat | None, k: int, d: int):
    """Centre (Q (d,d), r (d,)); default :meth:`Basis.default_center`."""
    if center is None:
        return Basis.default_center(k, d)
    if center.origin is not None or center.direction is not None:
        if k != 1:
            raise InvalidInputError("basis.center: origin/direction describe a line (k = 1)",
                                    "basis.center.origin")
        o = as_array(center.origin, "basis.center.origin", (d,))
        v = as_array(center.direction, "basis.center.direction", (d,))
        with _within("basis.center", {"origins": "origin", "directions": "direction"}):
            Q, r = Flats.from_rays(o[None], v[None]).quadrics()
        return Q[0], r[0]
    if center.A is not None or center.b is not None:
        A = as_array(center.A, "basis.center.A", (d, k))
        b = as_array(center.b, "basis.center.b", (d,))
        with _within("basis.center"):
            Q, r = Flats.from_parametric(A[None], b[None]).quadrics()
        return Q[0], r[0]
    if center.Q is not None or center.r is not None:
        Q = as_array(center.Q, "basis.center.Q", (d, d))
        r = as_array(center.r, "basis.center.r", (d,))
        with _within("basis.center"):
            Flats.from_quadrics(Q[None], r[None], k)
        return Q, r
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


def spec_dict(spec) -> dict:
    if spec is None:
        spec = TangentSimplexBasis()
    return spec.model_dump(exclude_none=True)
