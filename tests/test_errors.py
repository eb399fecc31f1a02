"""The one error table: class -> HTTP status, used by the service, inverted by the client."""
from __future__ import annotations

import httpx
import pytest

from flatserve import errors as le
from flatserve.service import status as fe
from flatserve.client import Client, ServiceError


#: status -> the classes (and their subclasses) the service answers it for
STATUS_OF = {
    404: [fe.FieldNotFoundError],
    409: [fe.FieldExistsError, fe.TooManyFieldsError],
    413: [fe.BatchTooLargeError, fe.BodyTooLargeError, fe.CostLimitError, fe.LimitExceededError],
    422: [le.InvalidFlatError, le.WeightsError, le.BasisError, fe.IdempotencyConflictError,
         ValueError],
    429: [fe.BacklogFullError],
    500: [le.FlatserveError, RuntimeError, KeyError],
    503: [fe.NotReadyError, fe.StorageError, fe.DataDirInUseError, le.SnapshotError],
    507: [fe.StorageFullError],
}


@pytest.mark.parametrize("exc, status", [(cls("x"), status) for status, classes in STATUS_OF.items()
                                         for cls in classes])
def test_status_of_walks_the_mro(exc, status):
    assert fe.status_of(exc) == status


def test_service_uses_the_library_table():
    from flatserve.service.http import errors as se
    for cls in fe.HTTP_STATUS:
        assert se.status_of(cls("x")) == fe.HTTP_STATUS[cls]
    assert se.status_of(se.ApiError(415, "x")) == 415
    # the limit errors live in the library only: the service keeps no copies
    assert not hasattr(se, "TooManyFieldsError") and not hasattr(se, "NotReadyError")


def test_error_class_inverts_the_table():
    for status in set(fe.HTTP_STATUS.values()):
        cls = fe.error_class(status)
        assert fe.HTTP_STATUS[cls] == status
        assert next(c for c, s in fe.HTTP_STATUS.items() if s == status) is cls
    assert fe.error_class(401) is None and fe.error_class(500) is None


def _client_answering(status, detail):
    """A Client whose every request gets ``status`` with ``{"detail": detail}``."""
    transport = httpx.MockTransport(lambda request: httpx.Response(status, json={"detail": detail}))
    return Client(http=httpx.Client(transport=transport, base_url="http://test"), retries=0)


@pytest.mark.parametrize("status, base", [(404, fe.FieldNotFoundError), (409, fe.FieldExistsError),
                                          (413, fe.LimitExceededError), (429, fe.BacklogFullError),
                                          (422, le.InvalidInputError), (503, fe.NotReadyError),
                                          (507, fe.StorageFullError)])
def test_client_raises_the_library_class(status, base):
    detail = [{"loc": ["body", "origins"], "msg": "bad", "type": "x"}] if status == 422 else "why"
    with pytest.raises(base) as err:
        _client_answering(status, detail).health()
    exc = err.value
    assert isinstance(exc, ServiceError)
    assert fe.status_of(exc) == status  # the round trip through the table
    assert exc.status == status and exc.detail == detail
    if status == 422:
        assert exc.argument == "origins"


def test_client_other_statuses_are_service_errors():
    with pytest.raises(ServiceError) as err:
        _client_answering(401, "no key").health()
    assert type(err.value) is ServiceError and err.value.status == 401
    assert "no key" in str(err.value)
