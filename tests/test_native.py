from flatserve import _native


def test_extension_reports_cgal_version():
    assert _native.CGAL_VERSION.startswith("5.")
