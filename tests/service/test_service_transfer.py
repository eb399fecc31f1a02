"""Export a field as one file and import it on another deployment: the imported field
answers bit for bit as the exported one (every kind of field, batches of every form,
rejected rows), survives a restart, a repeated import stores nothing twice and
completes one that failed half-way, and a file that is not an export is a 4xx."""
from __future__ import annotations

import contextlib
import io
import json
import math

import numpy as np
import pytest

from flatserve.contract import expected_copies
from flatserve.errors import InvalidInputError
from flatserve.flats import Flats, to_parametric
from flatserve.service.rooms.costs import cells_per_sample
from flatserve.service.status import FieldExistsError

from tests.harness.fields import ONE_CHART, paper_rays
from tests.harness.service import started

NPZ = "application/x-npz"


@pytest.fixture
def deployments(make_app, tmp_path):
    """Two servers on their own data directories: ``(source, target)`` as (tc, client)."""
    made = [started(make_app(data_dir=tmp_path / n)) for n in ("source", "target")]
    yield made
    for tc, _ in made:
        tc.__exit__(None, None, None)


def _fill(c, name, rng, *, oriented=False):
    """Batches of every form (rays, (A, b), (Q, r)), one with rejected rows, one
    acknowledged before its insert (wait=false)."""
    o, v = paper_rays(rng, 400)
    c.upload_rays(name, o, v, rng.uniform(size=(400, 2)))
    o, v = paper_rays(rng, 300)
    v[::5] = [1.0, 0.2, 0.01]  # outside a one chart's domain
    c.upload_rays(name, o, v, rng.uniform(size=(300, 2)), wait=False)
    if not oriented:
        A, b = to_parametric(*Flats.from_rays(*paper_rays(rng, 200)).quadrics(), 1)
        c.upload(name, rng.uniform(size=(200, 2)), A=A, b=b)
        Q, r = Flats.from_rays(*paper_rays(rng, 150)).quadrics()
        c.upload(name, rng.uniform(size=(150, 2)), Q=Q, r=r)
    c.wait_indexed(name)


KINDS = {
    "covering-atlas": {},
    "oriented-atlas": {"oriented": True},
    "one-chart": {"basis": ONE_CHART},
    "samples-atlas": {"basis": {"kind": "atlas", "atlas": "samples", "samples": {
        "origins": [[0, 0, -3], [0.3, 0, -3], [0, 0.3, -3]],
        "directions": [[0, 0, 1], [0.2, 0, 1], [0, 0.2, 1]]}}},
}


def dies_at_the_third(upload):
    """``upload`` failing at its third call (the disk gone mid-import), as it was before."""
    calls = []

    def upload_or_die(*args, **kw):
        calls.append(1)
        if len(calls) == 3:
            raise OSError("the disk went away")
        return upload(*args, **kw)

    return upload_or_die


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_an_imported_field_answers_bit_for_bit(deployments, rng, kind):
    (ta, a), (tb, b) = deployments
    a.create_field("src", channels=2, **KINDS[kind])
    _fill(a, "src", rng, oriented=KINDS[kind].get("oriented", False))
    data = a.export_field("src")
    rep = b.import_field("copy", data)
    src = a.describe("src", verbose=True)
    assert rep["source"] == "src" and rep["batches"] == len(a.batches("src"))
    assert rep["replayed_batches"] == 0 and rep["nsamples"] == src["nsamples"]
    dst = b.describe("copy", verbose=True)
    for key in ("k", "d", "channels", "oriented", "nsamples", "nrejected", "nvertices",
                "nsimplex", "basis", "atlas", "charts", "ncharts"):
        assert dst.get(key) == src.get(key), key
    assert [(x["rows"], x["accepted"]) for x in b.batches("copy")] == \
        [(x["rows"], x["accepted"]) for x in a.batches("src")]
    qo, qv = paper_rays(rng, 3000)
    want = a.query_rays("src", qo, qv, weights=kind == "one-chart")
    got = b.query_rays("copy", qo, qv, weights=kind == "one-chart")
    assert want.inside.sum() > 1000
    np.testing.assert_array_equal(got.values, want.values)
    np.testing.assert_array_equal(got.inside, want.inside)
    if kind == "one-chart":
        np.testing.assert_array_equal(got.ids, want.ids)
        np.testing.assert_array_equal(got.weights, want.weights)


def test_the_export_is_a_plain_npz_and_the_import_survives_a_restart(make_app, tmp_path, rng):
    tc, a = started(make_app(data_dir=tmp_path / "a"))
    a.create_field("f", channels=2, basis=ONE_CHART)
    _fill(a, "f", rng)
    r = tc.get("/v1/fields/f/export")
    assert r.headers["content-type"] == NPZ and "f.flatserve.npz" in r.headers["content-disposition"]
    with np.load(io.BytesIO(r.content), allow_pickle=False) as z:
        manifest = json.loads(bytes(z["manifest"]))
        assert manifest["field"] == "f" and manifest["format"] == 1
        assert [bt["rows"] for bt in manifest["batches"]] == [400, 300, 200, 150]
        assert z["values"].shape == (1050, 2) and z["rays_origins"].shape == (700, 3)
    qo, qv = paper_rays(rng, 500)
    want = a.query_rays("f", qo, qv)
    tc.__exit__(None, None, None)
    tb, b = started(make_app(data_dir=tmp_path / "b"))
    b.import_field("f", r.content)
    tb.__exit__(None, None, None)
    tb, b = started(make_app(data_dir=tmp_path / "b"))  # restored from its log
    try:
        np.testing.assert_array_equal(b.query_rays("f", qo, qv).values, want.values)
    finally:
        tb.__exit__(None, None, None)


def test_a_repeated_import_completes_a_failed_one_and_stores_nothing_twice(deployments, rng,
                                                                           monkeypatch):
    (_, a), (tb, b) = deployments
    a.create_field("f", channels=2, basis=ONE_CHART)
    _fill(a, "f", rng)
    data = a.export_field("f")
    uploads = tb.app.state.rooms.uploads
    real = uploads.upload
    monkeypatch.setattr(uploads, "upload", dies_at_the_third(real))
    with pytest.raises(Exception):
        b.import_field("g", data)
    assert len(b.batches("g")) == 2
    monkeypatch.setattr(uploads, "upload", real)
    rep = b.import_field("g", data)
    assert rep["replayed_batches"] == 2 and rep["batches"] == 4
    again = b.import_field("g", data)
    assert again["replayed_batches"] == 4 and again["accepted"] == 0
    assert [x["rows"] for x in b.batches("g")] == [400, 300, 200, 150]
    assert b.describe("g")["nsamples"] == a.describe("f")["nsamples"]
    # a field of that name with another definition is not overwritten
    b.create_field("other", channels=2)
    with pytest.raises(FieldExistsError, match="another definition"):
        b.import_field("other", data)
    assert b.batches("other") == []


def _npz(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _with_manifest(data: bytes, edit) -> bytes:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    m = json.loads(bytes(arrays["manifest"]))
    edit(m, arrays)
    arrays["manifest"] = np.frombuffer(json.dumps(m).encode(), np.uint8)
    return _npz(**arrays)


def test_a_body_that_is_not_an_export_is_a_4xx_naming_what(deployments, rng):
    (_, a), (tb, b) = deployments
    a.create_field("f", channels=2, basis=ONE_CHART)
    _fill(a, "f", rng)
    good = a.export_field("f")
    a.create_field("planes", k=2, d=4, channels=2)  # an atlas of 59 charts

    def rows(m, arrays):
        m["batches"][0]["rows"] += 1

    def spec(m, arrays):
        m["spec"]["channels"] = 1000

    def kind(m, arrays):  # the atlas still charts planes
        m["spec"]["k"] = 1

    def relative(m, arrays):  # a flag that is not one
        m["spec"]["atlas"]["relative"] = "yes"

    def fmt(m, arrays):
        m["format"] = 99

    def values(m, arrays):
        arrays["values"] = arrays["values"][:, :1]

    cases = {
        "no manifest": (_npz(values=np.zeros((2, 2))), 422, "not a flatserve export"),
        "rows": (_with_manifest(good, rows), 422, "rays_origins"),
        "spec": (_with_manifest(good, spec), 422, "manifest.spec.channels: Input should be "
                 "less than or equal to 64, got 1000"),
        "format": (_with_manifest(good, fmt), 422, "format 99"),
        "kind": (_with_manifest(a.export_field("planes"), kind), 422,
                 "atlas: charts 2-flats in R^4, the field is defined for 1-flats in R^4"),
        "relative": (_with_manifest(a.export_field("planes"), relative), 422,
                     "relative: expected true or false, got 'yes'"),
        "values": (_with_manifest(good, values), 422, "values: expected"),
        "not a zip": (b"hello, world", 422, "not a valid .npz"),
        "empty": (b"", 422, "empty body"),
    }
    for case, (body, status, words) in cases.items():
        r = tb.post("/v1/fields/x/import", content=body, headers={"Content-Type": NPZ})
        assert r.status_code == status and words in r.text, (case, r.status_code, r.text)
    r = tb.post("/v1/fields/x/import", content=good, headers={"Content-Type": "application/json"})
    assert r.status_code == 415
    assert [f["name"] for f in b.list_fields()] == []  # nothing was created
    with pytest.raises(InvalidInputError):
        b.import_field("-bad", good)  # not a field name


def _with_raw_manifest(data: bytes, raw: bytes) -> bytes:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["manifest"] = np.frombuffer(raw, np.uint8)
    return _npz(**arrays)


def test_a_deeply_nested_or_unparseable_manifest_is_a_422_naming_it(deployments, rng):
    """Nesting past any export's (the JSON parser's RecursionError beyond ~1000 levels,
    or under it a structure later steps would recurse into) and bytes that are not JSON
    are a 422 at ``["body", "manifest"]``, never a 500; nothing is created and the
    connection goes on serving."""
    (_, a), (tb, b) = deployments
    a.create_field("f", channels=2, basis=ONE_CHART)
    _fill(a, "f", rng)
    good = a.export_field("f")
    with np.load(io.BytesIO(good), allow_pickle=False) as z:
        text = bytes(z["manifest"]).decode()

    def nested(depth: int) -> str:
        return "[" * depth + "]" * depth

    cases = {
        "whole": (nested(100_000).encode(), "nested"),
        "in spec": (text.replace('"spec": {', f'"spec": {{"x": {nested(100_000)}, ', 1).encode(),
                    "nested"),
        "in batches": (text.replace('"batches": [', f'"batches": [{nested(500)}, ', 1).encode(),
                       "nested"),
        "objects": (("{" + '"a": {' * 5000 + "}" * 5001).encode(), "nested"),
        "not JSON": (b'{"format": 1,', "not JSON"),
        "not UTF-8": (b'{"field": "\xff"}', "not JSON"),
    }
    for case, (raw, words) in cases.items():
        r = tb.post("/v1/fields/x/import", content=_with_raw_manifest(good, raw),
                    headers={"Content-Type": NPZ})
        assert r.status_code == 422, (case, r.status_code, r.text[:300])
        err = r.json()["detail"][0]
        assert err["loc"] == ["body", "manifest"] and words in err["msg"], (case, err)
        assert err["msg"].startswith("manifest: ") and len(err["msg"]) < 300, (case, err)
    assert [f["name"] for f in b.list_fields()] == []  # nothing was created
    assert b.import_field("x", good)["batches"] == 4  # the same connection serves on


def _post(tc, name: str, body: bytes):
    return tc.post(f"/v1/fields/{name}/import", content=body, headers={"Content-Type": NPZ})


def _refused(tc, c, body: bytes, status: int, member: str, words: str = "") -> None:
    """The import of ``body`` is refused with ``status``, naming ``member``, and leaves
    no field and no batch (the target server holds no field before)."""
    r = _post(tc, "x", body)
    assert r.status_code == status, (member, r.status_code, r.text[:400])
    detail = r.json()["detail"]
    if status == 422:
        assert detail[0]["loc"] == ["body", *member.split(".")], (member, detail)
        detail = detail[0]["msg"]
    assert detail.startswith(member) and words in detail, (member, detail)
    assert c.list_fields() == [], member


def test_a_manifest_is_held_to_the_create_and_upload_limits_before_anything_is_stored(
        make_app, tmp_path, rng):
    """``tiles``, ``copies``, ``channels``, ``k``/``d`` and ``oriented`` of the file's
    definition get the limits a create request gets (``tiles`` 1-64 or "auto",
    ``copies`` 1-3); ``format`` is the integer 1 (not ``true``), ``export_id`` a short
    token (it goes into Idempotency-Keys), ``seq`` its batch's own, a batch at most
    ``max_batch_rows`` rows and the file at most ``max_import_batches`` batches. Each
    is refused naming the member, and nothing is stored."""
    ta, a = started(make_app(data_dir=tmp_path / "a"))
    tb, b = started(make_app(data_dir=tmp_path / "b", max_batch_rows=350,
                             max_import_batches=3))
    try:
        a.create_field("f", channels=2, basis=ONE_CHART)
        _fill(a, "f", rng)  # batches of 400, 300, 200 and 150 rows
        good = a.export_field("f")
        a.create_field("atlas", channels=2)
        a.upload_rays("atlas", *paper_rays(rng, 100), rng.uniform(size=(100, 2)))
        atlas = a.export_field("atlas")

        def edit(data: bytes, **spec):
            def change(m, arrays):
                m["spec"].update(spec)
            return _with_manifest(data, change)

        def top(data: bytes, **members):
            def change(m, arrays):
                m.update(members)
            return _with_manifest(data, change)

        def drop_batches(m, arrays):  # the first two batches' rows, no longer listed
            m["batches"] = m["batches"][2:]
            for name in ("rays_origins", "rays_directions"):
                arrays[name] = arrays[name][:0]
            arrays["values"] = arrays["values"][700:]

        small = _with_manifest(good, drop_batches)  # 200 + 150 rows

        def twice(m, arrays):
            m["batches"][1]["seq"] = m["batches"][0]["seq"]

        spec = "manifest.spec"
        cases = [
            (edit(small, tiles=1000), 422, f"{spec}.tiles", "less than or equal to 64"),
            (edit(small, tiles=10**7), 422, f"{spec}.tiles", "less than or equal to 64"),
            (edit(small, tiles=0), 422, f"{spec}.tiles", "greater than or equal to 1"),
            (edit(small, tiles="many"), 422, f"{spec}.tiles", "'auto'"),
            (edit(small, copies=0), 422, f"{spec}.copies", "greater than or equal to 1"),
            (edit(small, copies=-3), 422, f"{spec}.copies", "greater than or equal to 1"),
            (edit(small, copies=1000), 422, f"{spec}.copies", "less than or equal to 3"),
            (edit(small, copies=True), 422, f"{spec}.copies", "valid integer"),
            (edit(small, channels=0), 422, f"{spec}.channels", "greater than or equal to 1"),
            (edit(small, d=9), 422, f"{spec}.d", "less than or equal to 8"),
            (edit(small, roundtrip_tol=0.0), 422, f"{spec}.roundtrip_tol", "greater than"),
            (edit(atlas, tiles=2), 422, f"{spec}.tiles", "one chart"),
            (_with_manifest(atlas, lambda m, _: m["spec"]["atlas"].update(oriented="yes")),
             422, f"{spec}.oriented", "valid boolean"),
            (top(small, format=True), 422, "manifest.format", "format True"),
            (top(small, format=1.0), 422, "manifest.format", "format 1.0"),
            (top(small, export_id="a" * 129), 422, "manifest.export_id", "1-128"),
            (top(small, export_id="ab\r\nX-Evil: 1"), 422, "manifest.export_id", "1-128"),
            (top(small, export_id={"a": 1}), 422, "manifest.export_id", "1-128"),
            (top(small, export_id=""), 422, "manifest.export_id", "1-128"),
            (top(small, field=["f"]), 422, "manifest.field", "name"),
            (_with_manifest(small, twice), 422, "manifest.batches.1", "listed twice"),
            (top(small, batches=[{"seq": True, "form": "flats", "rows": 200},
                                 {"seq": 2, "form": "flats", "rows": 150}]),
             422, "manifest.batches.0", "seq >= 1"),
            (good, 413, "manifest.batches", "FLATSERVE_MAX_IMPORT_BATCHES"),  # 4 > 3
        ]
        for body, status, member, words in cases:
            _refused(tb, b, body, status, member, words)
        # 3 batches, the first of 400 rows > max_batch_rows
        _refused(tb, b, _with_manifest(good, lambda m, arrays: m["batches"].pop()), 413,
                 "manifest.batches.0", "FLATSERVE_MAX_BATCH_ROWS")
        assert b.import_field("x", small)["batches"] == 2  # within every limit
    finally:
        tb.__exit__(None, None, None)
        ta.__exit__(None, None, None)


def test_a_bad_batch_anywhere_in_the_file_refuses_the_whole_import(deployments, rng):
    """A NaN, a zero direction or a batch whose rows an upload refuses, in any batch
    of the file (the last one too), is a 422 naming the file's member and the batch,
    before the field is created or any batch stored; the file mended imports whole."""
    (_, a), (tb, b) = deployments
    a.create_field("f", channels=2, basis=ONE_CHART)
    _fill(a, "f", rng)  # batches 0-3: rays 400, rays 300, parametric 200, flats 150
    good = a.export_field("f")
    a.create_field("rays", channels=2, oriented=True)
    a.upload_rays("rays", *paper_rays(rng, 100), rng.uniform(size=(100, 2)))
    a.upload_rays("rays", *paper_rays(rng, 100), rng.uniform(size=(100, 2)))
    oriented = a.export_field("rays")

    def put(member: str, row: int, value):
        def change(m, arrays):
            arrays[member] = arrays[member].copy()
            arrays[member][row] = value
        return change

    def as_lines(m, arrays):  # the oriented field's second batch given as (A, b)
        o, v = arrays["rays_origins"][100:], arrays["rays_directions"][100:]
        A, bb = to_parametric(*Flats.from_rays(o, v).quadrics(), 1)
        arrays["rays_origins"], arrays["rays_directions"] = (arrays["rays_origins"][:100],
                                                             arrays["rays_directions"][:100])
        arrays["parametric_A"], arrays["parametric_b"] = A, bb
        m["batches"][1]["form"] = "parametric"

    cases = [
        (put("values", 1049, np.nan), "values", "batch 3 (seq 4"),
        (put("rays_directions", 450, 0.0), "rays_directions", "batch 1 (seq 2"),
        (put("parametric_A", 199, np.inf), "parametric_A", "batch 2 (seq 3"),
        (put("flats_r", 149, np.nan), "flats_r", "batch 3 (seq 4"),
    ]
    for change, member, words in cases:
        _refused(tb, b, _with_manifest(good, change), 422, member, words)
    _refused(tb, b, _with_manifest(oriented, as_lines), 422, "parametric_A",
             "batch 1 (seq 2): this atlas is oriented")
    assert b.import_field("x", good)["nsamples"] == a.describe("f")["nsamples"]


def test_a_stored_definition_beyond_the_create_limits_fails_its_field_only(make_app,
                                                                           tmp_path, rng):
    """A create entry in the log whose definition no create makes (written to the
    storage directly, as a faulty version, an old import or a hand edit would:
    ``copies`` 0, ``tiles`` 65, ``channels`` 0, tiles on an atlas, an atlas of other
    flats than the field's) is never built: the follower applying it and a restart
    restoring it mark that field failed naming the member (503 for its requests,
    ``failed`` in the listing), the server starts, and the other fields serve on
    (bit for bit); a failed field can be deleted."""
    tc, c = started(make_app(data_dir=tmp_path / "d"))
    c.create_field("good", channels=2, basis=ONE_CHART)
    c.upload_rays("good", *paper_rays(rng, 400), rng.uniform(size=(400, 2)))
    c.create_field("atlas", channels=2)
    c.upload_rays("atlas", *paper_rays(rng, 400), rng.uniform(size=(400, 2)))
    qo, qv = paper_rays(rng, 500)
    want = {n: c.query_rays(n, qo, qv).values for n in ("good", "atlas")}
    rooms = tc.app.state.rooms
    one = rooms.storage.field(rooms.catalogue.get("good").id)
    at = rooms.storage.field(rooms.catalogue.get("atlas").id)
    bad = {
        "copies0": (dict(one.spec, copies=0), one.basis, "spec.copies"),
        "tiles65": (dict(one.spec, tiles=65), one.basis, "spec.tiles"),
        "channels0": (dict(one.spec, channels=0), one.basis, "spec.channels"),
        "tiled-atlas": (dict(at.spec, tiles=2), at.basis, "spec.tiles"),
        "planes": (dict(at.spec, k=2), at.basis, "spec.atlas"),
    }
    for name, (spec, basis, _) in bad.items():
        _, pos = rooms.storage.create_field(name, spec, basis)
        assert rooms.follower.wait_applied(pos, 30)

    def check(tc, c):
        states = {f["name"]: f["state"] for f in c.list_fields()}
        assert states == {"good": "ready", "atlas": "ready", **dict.fromkeys(bad, "failed")}
        for name, (_, _, member) in bad.items():
            for r in (tc.get(f"/v1/fields/{name}"),
                      tc.post(f"/v1/fields/{name}/query",
                              json={"origins": qo[:2].tolist(), "directions": qv[:2].tolist()})):
                assert r.status_code == 503 and member in r.text, (name, r.status_code, r.text)
        for name, values in want.items():
            np.testing.assert_array_equal(c.query_rays(name, qo, qv).values, values)

    check(tc, c)
    tc.__exit__(None, None, None)
    tc, c = started(make_app(data_dir=tmp_path / "d"))  # restored from the log
    try:
        check(tc, c)
        c.upload_rays("good", *paper_rays(rng, 100), rng.uniform(size=(100, 2)))
        c.delete_field("copies0")
        assert "copies0" not in {f["name"] for f in c.list_fields()}
    finally:
        tc.__exit__(None, None, None)


def _servers(stack, make_app, tmp_path):
    """``server(name, **settings)``: a server on its own data directory, closed with
    ``stack``: its ``(TestClient, Client)``."""
    def server(name, **settings):
        tc, c = started(make_app(data_dir=tmp_path / name, **settings))
        stack.callback(tc.__exit__, None, None, None)
        return tc, c

    return server


def test_an_import_past_the_cost_guard_is_refused_whole(make_app, tmp_path, rng, monkeypatch):
    """``max_simplices`` judges all the file's batches at once, before any is stored, by
    the upload's own estimate: a file whose first batches would pass alone but not the
    whole is a 413 naming the field and leaves no field (it used to store the batches
    before the one refused). A repeated import counts only the batches still missing."""
    with contextlib.ExitStack() as stack:
        server = _servers(stack, make_app, tmp_path)

        ta, a = server("a")
        a.create_field("f", channels=2, basis=ONE_CHART)
        _fill(a, "f", rng)
        data = a.export_field("f")
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            rows = [bt["rows"] for bt in json.loads(bytes(z["manifest"]))["batches"]]
        # the guard's estimate for a new field: every row of the file, each stored in
        # the charts holding it, times the cells per sample of the field's dimension
        field = ta.app.state.rooms.catalogue.get("f").field
        per_row = cells_per_sample(field.ndim) * expected_copies(field)
        first_two, whole = sum(rows[:2]) * per_row, sum(rows) * per_row
        # b: the first two batches would pass alone, the whole file not; c: the whole passes
        tb, b = server("b", max_simplices=int((first_two + whole) / 2), min_field_samples=0)
        tc, c = server("c", max_simplices=math.ceil(whole), min_field_samples=0)
        r = _post(tb, "x", data)
        assert r.status_code == 413, r.text
        assert b.list_fields() == [], "a refused import left a field"
        detail = r.json()["detail"]
        assert detail.startswith("field 'x': ") and "after this import" in detail, detail
        assert f"{sum(rows)} new" in detail and "FLATSERVE_MAX_SIMPLICES" in detail, detail
        # the whole file passes c (an import half stored, then repeated: the samples
        # held + the rows missing, fewer than the file's rows)
        uploads = tc.app.state.rooms.uploads
        real = uploads.upload
        monkeypatch.setattr(uploads, "upload", dies_at_the_third(real))
        with pytest.raises(OSError):
            c.import_field("x", data)
        monkeypatch.setattr(uploads, "upload", real)
        assert [x["rows"] for x in c.batches("x")] == rows[:2]
        rep = c.import_field("x", data)
        assert rep["replayed_batches"] == 2 and rep["nsamples"] == a.describe("f")["nsamples"]


def test_two_imports_into_one_field_at_once_are_judged_one_after_the_other(
        make_app, tmp_path, rng, monkeypatch):
    """Two files of one definition imported into one field at once, each within
    ``max_simplices`` alone but not both: the second is judged once the first's batches
    are stored, and refused whole (it used to be judged against the field as it was
    before either, and both were stored); an upload while an import stores its batches
    counts the rows the import has yet to store."""
    import threading

    from flatserve.service.status import CostLimitError, CostPendingError

    with contextlib.ExitStack() as stack:
        server = _servers(stack, make_app, tmp_path)

        ta, a = server("a")
        files = []
        for name in ("f", "g"):
            a.create_field(name, channels=2, basis=ONE_CHART)
            _fill(a, name, rng)
            files.append(a.export_field(name))
        field = ta.app.state.rooms.catalogue.get("f").field
        with np.load(io.BytesIO(files[0]), allow_pickle=False) as z:  # every row counts
            rows = sum(bt["rows"] for bt in json.loads(bytes(z["manifest"]))["batches"])
        one = rows * cells_per_sample(field.ndim) * expected_copies(field)
        tb, b = server("b", max_simplices=math.ceil(1.5 * one), min_field_samples=0)
        rooms = tb.app.state.rooms
        # the first import's first batch waits until the second import has started
        started_second, first_in = threading.Event(), threading.Event()
        real = rooms.uploads.upload

        def upload(*args, **kw):
            if not first_in.is_set():
                first_in.set()
                started_second.wait(10)
                # and an upload now counts the rows the import has yet to store: one
                # that would pass alone waits (429) until they are in
                e = rooms.catalogue.get("x")
                assert e.reserved == rows
                n = int(0.6 * rows)
                with pytest.raises(CostPendingError):
                    real(e, Flats.from_rays(*paper_rays(rng, n)), rng.uniform(size=(n, 2)),
                         None)
            return real(*args, **kw)

        monkeypatch.setattr(rooms.uploads, "upload", upload)
        got: dict = {}

        def run(i):
            try:
                got[i] = rooms.transfer.import_field("x", files[i])
            except Exception as exc:  # noqa: BLE001 (the outcome is the test's)
                got[i] = exc

        first = threading.Thread(target=run, args=(0,))
        first.start()
        assert first_in.wait(30)
        second = threading.Thread(target=run, args=(1,))
        second.start()
        second.join(1.0)  # it waits for the first: it cannot have been judged yet
        assert second.is_alive() and 1 not in got
        started_second.set()
        first.join(120)
        second.join(120)
        assert not isinstance(got[0], Exception), got[0]
        assert isinstance(got[1], (CostLimitError, CostPendingError)), got[1]
        assert "field 'x'" in str(got[1])
        assert b.describe("x")["nsamples"] == a.describe("f")["nsamples"]
        assert rooms.catalogue.get("x").reserved == 0
