from flatserve import _native


def test_extension_reports_cgal_version():
    assert _native.CGAL_VERSION.startswith("5.")


def test_extension_errors_subclass_the_library_classes():
    import pytest

    from flatserve.errors import FlatserveError, SnapshotError
    assert issubclass(_native.core.SnapshotError, SnapshotError)
    with pytest.raises(SnapshotError) as err:
        _native.Triangulation.from_bytes(b"not a snapshot")
    assert isinstance(err.value, FlatserveError) and isinstance(err.value, ValueError)


def test_extension_enums_compare_with_int8_arrays():
    import numpy as np

    from flatserve.coordinates import AMBIGUOUS, OK, REASONS, SINGULAR, Status, reason
    from flatserve.triangulation import LocateKind
    assert [int(s) for s in Status] == [0, 1, 2, 3] and OK is Status.OK
    assert set(REASONS) == set(Status) and reason(SINGULAR).startswith("singular")
    assert reason(7) == "status 7"
    status = np.array([OK, AMBIGUOUS, SINGULAR], dtype=np.int8)
    assert (status == AMBIGUOUS).tolist() == [False, True, False]
    assert [int(k) for k in LocateKind] == list(range(6))
    assert LocateKind.ON_VERTEX == 3 and LocateKind is _native.LocateKind
