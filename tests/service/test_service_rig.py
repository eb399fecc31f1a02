"""A field's ``rig`` (the cameras of a capture with depth, :class:`~flatserve.service.schemas.RigSpec`):
checked at create and wherever a stored definition is read (one check,
:func:`flatserve.service.rooms.specs.rig_of`), stored with the field, described, kept by a
restart, a replica applying the log and an export/import, and compared by a
same-name create with ``exist_ok``.

The rigs are random (seeded); the oracle of every kept rig is the one created, number
for number."""
from __future__ import annotations

import io
import json
import math
import os

import numpy as np
import pytest

from flatserve.service.schemas import MAX_RIG_EYES
from flatserve.service.status import FieldExistsError
from flatserve.service.log.storage import lock_data_dir
from tests.harness.fields import paper_rays
from tests.harness.service import started

NPZ = "application/x-npz"


def random_rig(rng, m: int = 5) -> dict:
    """``m`` eyes about 3 from a centre near the origin (JSON numbers)."""
    center = rng.normal(scale=0.1, size=3)
    e = rng.normal(size=(m, 3))
    eyes = center + 3.0 * e / np.linalg.norm(e, axis=1, keepdims=True)
    return {"eyes": eyes.tolist(), "center": center.tolist()}


def rig_body(name: str, rig, **kw) -> dict:
    """A create request of an oriented field of rays in R^3 with 2 channels and ``rig``."""
    return {"name": name, "k": 1, "d": 3, "channels": 2, "oriented": True, "rig": rig, **kw}


def test_a_field_created_with_a_rig_describes_it(api, rng):
    tc, c = api
    rig = random_rig(rng)
    r = tc.post("/v1/fields", json=rig_body("lf", rig))
    assert r.status_code == 201, r.text
    assert r.json()["rig"] == rig
    assert c.describe("lf")["rig"] == rig and c.describe("lf", verbose=True)["rig"] == rig
    # the same from the client, a DepthRig too; a field without one describes none
    from flatserve.lightfield.rig import DepthRig

    other = random_rig(rng, 7)
    info = c.create_field("lf2", channels=4, oriented=True, rig=DepthRig.from_dict(other))
    assert info["rig"] == other and info["channels"] == 4
    c.create_field("plain", channels=2, oriented=True)
    assert "rig" not in c.describe("plain")
    r = tc.post("/v1/fields", json=rig_body("nulled", None))
    assert r.status_code == 201 and "rig" not in r.json()
    # uploads hold its channels (colours and the depth channel)
    o, v = paper_rays(rng, 200)
    rep = c.upload_rays("lf", o, v, rng.uniform(size=(200, 2)))
    assert rep["accepted"] == 200


def _bad_shapes():
    ok = {"eyes": [[0.0, 0.0, -3.0], [3.0, 0.0, 0.0]], "center": [0.0, 0.0, 0.0]}
    many = [[3.0, 0.0, float(i) / MAX_RIG_EYES] for i in range(MAX_RIG_EYES + 1)]
    return {
        "one eye": (dict(ok, eyes=ok["eyes"][:1]), ["rig", "eyes"]),
        "too many eyes": (dict(ok, eyes=many), ["rig", "eyes"]),
        "an eye of 2": (dict(ok, eyes=[[0.0, 0.0], [3.0, 0.0, 0.0]]), ["rig", "eyes"]),
        "an eye of 4": (dict(ok, eyes=[[0.0, 0.0, 1.0, 2.0], [3.0, 0.0, 0.0]]), ["rig", "eyes"]),
        "a string": (dict(ok, eyes=[["0", 0.0, 1.0], [3.0, 0.0, 0.0]]), ["rig", "eyes"]),
        "a boolean": (dict(ok, eyes=[[True, 0.0, 1.0], [3.0, 0.0, 0.0]]), ["rig", "eyes"]),
        "eyes flat": (dict(ok, eyes=[0.0, 0.0, -3.0, 3.0, 0.0, 0.0]), ["rig", "eyes"]),
        "center of 2": (dict(ok, center=[0.0, 0.0]), ["rig", "center"]),
        "center a number": (dict(ok, center=0.0), ["rig", "center"]),
        "no center": ({"eyes": ok["eyes"]}, ["rig", "center"]),
        "no eyes": ({"center": ok["center"]}, ["rig", "eyes"]),
        "another member": (dict(ok, up=[0.0, 1.0, 0.0]), ["rig", "up"]),
        "a list": ([ok["eyes"], ok["center"]], ["rig"]),
    }


@pytest.mark.parametrize("case", sorted(_bad_shapes()))
def test_a_rig_of_another_shape_is_a_422_naming_the_member(api, case):
    tc, c = api
    rig, loc = _bad_shapes()[case]
    r = tc.post("/v1/fields", json=rig_body("bad", rig))
    assert r.status_code == 422, (case, r.text)
    assert r.json()["detail"][0]["loc"][1:1 + len(loc)] == loc, (case, r.text)
    assert "bad" not in [f["name"] for f in c.list_fields()]


@pytest.mark.parametrize("number", ["NaN", "Infinity", "-Infinity", "1e999"])
@pytest.mark.parametrize("member", ["eyes", "center"])
def test_a_rig_of_numbers_not_finite_is_a_422_naming_the_member(api, number, member):
    tc, _ = api
    eyes = "[[0, 0, -3], [3, 0, %s]]" % (number if member == "eyes" else "0")
    center = "[0, 0, %s]" % (number if member == "center" else "0")
    body = ('{"name": "bad", "k": 1, "d": 3, "channels": 2, "oriented": true, '
            '"rig": {"eyes": %s, "center": %s}}' % (eyes, center))
    r = tc.post("/v1/fields", content=body, headers={"Content-Type": "application/json"})
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"][1:3] == ["rig", member], r.text


@pytest.mark.parametrize("kind, words", [
    ({"oriented": False}, "oriented lines in R^3"),
    ({"oriented": None}, "oriented lines in R^3"),
    ({"channels": 1}, "at least 2 channels"),
    ({"d": 4}, "oriented lines in R^3"),
    ({"k": 0, "oriented": None}, "oriented lines in R^3"),
    ({"k": 2, "d": 4, "oriented": None}, "oriented lines in R^3"),
    ({"oriented": None, "basis": {"kind": "tangent_simplex"}}, "oriented lines in R^3"),
])
def test_a_rig_on_another_kind_of_field_is_a_422_naming_rig(api, rng, kind, words):
    tc, c = api
    body = {k: v for k, v in rig_body("bad", random_rig(rng), **kind).items() if v is not None}
    r = tc.post("/v1/fields", json=body)
    assert r.status_code == 422, (kind, r.text)
    err = r.json()["detail"][0]
    assert err["loc"] == ["body", "rig"] and words in err["msg"], (kind, err)
    assert "bad" not in [f["name"] for f in c.list_fields()]


def test_exist_ok_compares_the_rig(api, rng):
    """A same-name create with ``exist_ok`` takes the field when the rig asked is its
    rig (or none is asked, as ``oriented``); another rig, or one asked of a field
    without, is a 409 naming ``rig``."""
    _, c = api
    rig = random_rig(rng)
    first = c.create_field("lf", channels=2, oriented=True, rig=rig)
    again = c.create_field("lf", channels=2, oriented=True, rig=rig, exist_ok=True)
    assert again["rig"] == rig and again["created"] == first["created"]
    as_arrays = {"eyes": np.array(rig["eyes"]), "center": np.array(rig["center"])}
    assert c.create_field("lf", channels=2, oriented=True, rig=as_arrays, exist_ok=True)["rig"] == rig
    assert c.create_field("lf", channels=2, exist_ok=True)["rig"] == rig  # (not asked)
    moved = {"eyes": rig["eyes"], "center": np.add(rig["center"], 1e-9).tolist()}
    with pytest.raises(FieldExistsError, match="rig="):
        c.create_field("lf", channels=2, oriented=True, rig=moved, exist_ok=True)
    c.create_field("plain", channels=2, oriented=True)
    with pytest.raises(FieldExistsError, match="rig='none'"):
        c.create_field("plain", channels=2, oriented=True, rig=rig, exist_ok=True)


def test_a_restart_and_a_replica_keep_the_rig(make_app, tmp_path, rng):
    """Two replicas of one data directory (one lock for both, as ``serve --processes``):
    the one that did not create the field applies the create from the log with its
    rig; a restart restores it from the log too."""
    data = tmp_path / "data"
    fd = lock_data_dir(data)
    rig = random_rig(rng, 9)
    o, v = paper_rays(rng, 300)
    values = rng.uniform(size=(300, 3))
    try:
        (ta, a), (tb, b) = (started(make_app(data_dir=data, lock_fd=fd)) for _ in range(2))
        try:
            made = a.create_field("lf", channels=3, oriented=True, rig=rig)
            a.upload_rays("lf", o, v, values)
            seen = b.describe("lf", min_position=made["position"])
            assert seen["rig"] == rig and seen["channels"] == 3
        finally:
            ta.__exit__(None, None, None)
            tb.__exit__(None, None, None)
        tc, c = started(make_app(data_dir=data, lock_fd=fd))
        try:
            info = c.describe("lf")
            assert info["rig"] == rig and info["nsamples"] == 300
        finally:
            tc.__exit__(None, None, None)
    finally:
        os.close(fd)


def _with_manifest(data: bytes, edit) -> bytes:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    m = json.loads(bytes(arrays["manifest"]))
    edit(m)
    arrays["manifest"] = np.frombuffer(json.dumps(m).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def test_an_export_carries_the_rig_and_an_import_checks_it(api, rng):
    """The export's manifest holds the rig; the imported field has it; an existing field
    of the same definition but another rig is not the file's (409); a manifest whose
    rig no create accepts is a 422 naming ``manifest.spec.rig`` (nothing created)."""
    tc, c = api
    rig = random_rig(rng)
    c.create_field("lf", channels=2, oriented=True, rig=rig)
    o, v = paper_rays(rng, 300)
    c.upload_rays("lf", o, v, rng.uniform(size=(300, 2)))
    data = c.export_field("lf")
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        assert json.loads(bytes(z["manifest"]))["spec"]["rig"] == rig
    assert c.import_field("copy", data)["nsamples"] == 300
    assert c.describe("copy")["rig"] == rig
    again = c.import_field("copy", data)  # the same definition: taken, nothing twice
    assert again["replayed_batches"] == again["batches"] and again["nsamples"] == 300

    def moved(m):
        m["spec"]["rig"]["center"] = np.add(m["spec"]["rig"]["center"], 0.5).tolist()

    r = tc.post("/v1/fields/copy/import", content=_with_manifest(data, moved),
                headers={"Content-Type": NPZ})
    assert r.status_code == 409, r.text
    bad = {
        "one eye": lambda m: m["spec"]["rig"].update(eyes=m["spec"]["rig"]["eyes"][:1]),
        "one channel": lambda m: m["spec"].update(channels=1),
        "unoriented": lambda m: m["spec"]["atlas"].update(oriented=False),
        "a string": lambda m: m["spec"].update(rig="eyes"),
    }
    for case, edit in bad.items():
        r = tc.post("/v1/fields/bad/import", content=_with_manifest(data, edit),
                    headers={"Content-Type": NPZ})
        assert r.status_code == 422, (case, r.text)
        err = r.json()["detail"][0]
        assert err["loc"][:4] == ["body", "manifest", "spec", "rig"], (case, err)
    assert "bad" not in [f["name"] for f in c.list_fields()]


def test_a_stored_definition_with_a_bad_rig_fails_its_field_only(make_app, tmp_path, rng):
    """A create entry in the log whose rig no create accepts (written to the storage
    directly) is never built: the follower marks that field failed naming
    ``spec.rig``, as a restart does; the field with a good rig serves on."""
    tc, c = started(make_app(data_dir=tmp_path / "d"))
    try:
        c.create_field("lf", channels=2, oriented=True, rig=random_rig(rng))
        rooms = tc.app.state.rooms
        row = rooms.storage.field(rooms.catalogue.get("lf").id)
        rig = row.spec["rig"]
        bad = {
            "nan": dict(row.spec, rig=dict(rig, center=[0.0, math.nan, 0.0])),
            "channels1": dict(row.spec, channels=1),
            "flat": dict(row.spec, rig=dict(rig, eyes=[1.0, 2.0, 3.0])),
        }
        for name, spec in bad.items():
            _, pos = rooms.storage.create_field(name, spec, row.basis)
            assert rooms.follower.wait_applied(pos, 30)
        states = {f["name"]: f["state"] for f in c.list_fields()}
        assert states == {"lf": "ready", **dict.fromkeys(bad, "failed")}
        for name in bad:
            r = tc.get(f"/v1/fields/{name}")
            assert r.status_code == 503 and "spec.rig" in r.text, (name, r.text)
        assert c.describe("lf")["rig"] == rig
    finally:
        tc.__exit__(None, None, None)
