"""Turn JSON flat / basis specifications into arrays and a Basis (no math here:
everything is delegated to :mod:`flatserve.flats` and :mod:`flatserve.basis`)."""
from __future__ import annotations

from contextlib import contextmanager

import numpy as np

from .._validate import as_array
from ..errors import InvalidInputError
from .schemas import CenterFlat, FlatsBasis, TangentSimplexBasis


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


def flats_from(obj, k: int, d: int, prefix: str, max_rows: int | None = None,
               validate: bool = True):
    """(Q (n,d,d), r (n,d)) from an object with Q+r, A+b or origins+directions.

    ``validate=False`` keeps (Q, r) given directly unchecked (basis elements of a
    tangent simplex lie on the tangent plane, not on the manifold of flats)."""
    from .. import flats
    from .errors import BatchTooLargeError

    def get(name):
        return getattr(obj, name, None) if not isinstance(obj, dict) else obj.get(name)

    def rows_ok(a):
        if max_rows is not None and a.shape[0] > max_rows:
            raise BatchTooLargeError(f"{a.shape[0]} flats in one request; the limit is {max_rows}")
        return a

    if get("Q") is not None or get("r") is not None:
        Q = rows_ok(as_array(get("Q"), f"{prefix}.Q", ("n", d, d)))
        r = as_array(get("r"), f"{prefix}.r", (Q.shape[0], d))
        if validate:
            with _within(prefix):
                flats.validate(Q, r, k)
        return Q, r
    if get("A") is not None or get("b") is not None:
        A = rows_ok(as_array(get("A"), f"{prefix}.A", ("n", d, k)))
        b = as_array(get("b"), f"{prefix}.b", (A.shape[0], d))
        with _within(prefix):
            return flats.from_parametric(A, b)
    if get("origins") is not None or get("directions") is not None:
        if k != 1:
            raise InvalidInputError(f"{prefix}: origins/directions describe lines (k = 1), k = {k}",
                                    f"{prefix}.origins")
        o = rows_ok(as_array(get("origins"), f"{prefix}.origins", ("n", d)))
        v = as_array(get("directions"), f"{prefix}.directions", (o.shape[0], d))
        with _within(prefix):
            return flats.from_rays(o, v)
    raise InvalidInputError(f"{prefix}: give Q+r, A+b or origins+directions", prefix)


def center_flat(center: CenterFlat | None, k: int, d: int):
    """Centre (Q (d,d), r (d,)); default: span of the last k axes through the origin."""
    from .. import flats

    if center is None:
        A = np.eye(d)[:, d - k:]
        Q, r = flats.from_parametric(A[None], np.zeros((1, d)))
        return Q[0], r[0]
    if center.origin is not None or center.direction is not None:
        if k != 1:
            raise InvalidInputError("basis.center: origin/direction describe a line (k = 1)",
                                    "basis.center.origin")
        o = as_array(center.origin, "basis.center.origin", (d,))
        v = as_array(center.direction, "basis.center.direction", (d,))
        with _within("basis.center", {"origins": "origin", "directions": "direction"}):
            Q, r = flats.from_rays(o[None], v[None])
        return Q[0], r[0]
    if center.A is not None or center.b is not None:
        A = as_array(center.A, "basis.center.A", (d, k))
        b = as_array(center.b, "basis.center.b", (d,))
        with _within("basis.center"):
            Q, r = flats.from_parametric(A[None], b[None])
        return Q[0], r[0]
    if center.Q is not None or center.r is not None:
        Q = as_array(center.Q, "basis.center.Q", (d, d))
        r = as_array(center.r, "basis.center.r", (d,))
        with _within("basis.center"):
            flats.validate(Q[None], r[None], k)
        return Q, r
    return center_flat(None, k, d)


def build_basis(spec, k: int, d: int):
    """A :class:`flatserve.basis.Basis` from a basis spec (None: default tangent simplex)."""
    from ..basis import Basis

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


def check_field_basis(basis, k: int, d: int) -> None:
    """A field's basis must be full: m = (k+1)(d-k) + 1 flats passing Sec. 3's checks."""
    from ..errors import BasisError

    want = (k + 1) * (d - k) + 1
    if basis.m != want:
        raise InvalidInputError(
            f"basis: a field needs m = (k+1)(d-k)+1 = {want} flats, got {basis.m}", "basis")
    report = basis.check()
    if not report.ok:
        try:
            report.raise_for_failures()
        except BasisError as exc:
            raise InvalidInputError(f"basis: {exc}", "basis") from None
        raise InvalidInputError("basis: fails the checks of paper Sec. 3", "basis")
