"""Triangle meshes: loading (OFF/PLY/OBJ), normalising, the bunny, test meshes.

A mesh is two arrays: ``vertices`` (nv, 3) float64 and ``faces`` (nf, 3) int64
(vertex indices, one triangle a row). OFF files are read by a small reader
here (polygons are split into triangle fans); PLY and OBJ go through
`trimesh <https://trimesh.org>`_.

The Stanford bunny of the paper's Fig. 11 ships in Debian's ``libcgal-demo``
package as ``data/meshes/bunny00.off`` inside
``/usr/share/doc/libcgal-dev/data.tar.gz``; :func:`bunny_path` extracts it at
run time into a cache directory (it is never part of this repository).
"""
from __future__ import annotations

import os
import tarfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._validate import as_array
from ..errors import InvalidInputError

__all__ = [
    "Mesh",
    "load_mesh",
    "read_off",
    "normalize_to_unit_box",
    "bunny_path",
    "load_bunny",
    "box_mesh",
    "icosphere",
    "merge_meshes",
    "CGAL_DATA_TARBALL",
    "BUNNY_MEMBER",
]

#: Debian's libcgal-demo data archive holding the bunny.
CGAL_DATA_TARBALL = Path("/usr/share/doc/libcgal-dev/data.tar.gz")
#: Member of :data:`CGAL_DATA_TARBALL` with the paper's bunny (37,706 vertices).
BUNNY_MEMBER = "data/meshes/bunny00.off"


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh.

    Attributes
    ----------
    vertices : (nv, 3) float64
    faces : (nf, 3) int64
        Indices into ``vertices``, one triangle a row.
    """

    vertices: np.ndarray
    faces: np.ndarray

    def __post_init__(self):
        v = as_array(self.vertices, "vertices", (None, 3))
        f = as_array(self.faces, "faces", (None, 3), dtype=np.int64, finite=False)
        if f.size and (f.min() < 0 or f.max() >= v.shape[0]):
            raise InvalidInputError("faces: vertex index out of range", "faces")
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f)

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) lower and upper corner of the bounding box."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    def face_normals(self) -> np.ndarray:
        """(nf, 3) unit normals (right-hand rule; zero for degenerate faces)."""
        a, b, c = (self.vertices[self.faces[:, i]] for i in range(3))
        n = np.cross(b - a, c - a)
        length = np.linalg.norm(n, axis=1, keepdims=True)
        return np.divide(n, length, out=np.zeros_like(n), where=length > 0)

    def vertex_normals(self) -> np.ndarray:
        """(nv, 3) unit normals: area-weighted sums of the adjacent face normals."""
        a, b, c = (self.vertices[self.faces[:, i]] for i in range(3))
        n = np.cross(b - a, c - a)  # length = twice the area: area weighting
        acc = np.zeros_like(self.vertices)
        for i in range(3):
            np.add.at(acc, self.faces[:, i], n)
        length = np.linalg.norm(acc, axis=1, keepdims=True)
        return np.divide(acc, length, out=np.zeros_like(acc), where=length > 0)


def _fan(polys: list[list[int]]) -> np.ndarray:
    tris = [(p[0], p[i], p[i + 1]) for p in polys for i in range(1, len(p) - 1)]
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


def read_off(path: str | os.PathLike) -> Mesh:
    """Read an OFF file (also COFF/NOFF headers; colours and normals ignored).

    Parameters
    ----------
    path : path-like
        An ASCII OFF file (``#`` starts a comment).

    Returns
    -------
    Mesh
        Polygons with more than three corners are split into triangle fans.
    """
    with open(path, "r", encoding="ascii", errors="replace") as fh:
        tokens = []
        for line in fh:
            line = line.split("#", 1)[0].strip()
            if line:
                tokens.append(line)
    if not tokens or not tokens[0].upper().endswith("OFF"):
        raise InvalidInputError(f"path: {path} is not an OFF file", "path")
    header = tokens[0].split()
    try:
        # counts may sit on the header line ("OFF 3 1 0") or on the next line
        if header[1:]:
            counts, body = header[1:4], tokens[1:]
        else:
            counts, body = tokens[1].split()[:3], tokens[2:]
        nv, nf = int(counts[0]), int(counts[1])
        verts = np.array([body[i].split()[:3] for i in range(nv)], dtype=np.float64)
        polys = []
        for line in body[nv : nv + nf]:
            parts = line.split()
            cnt = int(parts[0])
            polys.append([int(x) for x in parts[1 : 1 + cnt]])
    except (IndexError, ValueError) as exc:
        raise InvalidInputError(f"path: malformed OFF file {path}: {exc}", "path") from None
    return Mesh(verts.reshape(-1, 3), _fan(polys))


def load_mesh(path: str | os.PathLike) -> Mesh:
    """Load a triangle mesh from an OFF, PLY or OBJ file.

    Parameters
    ----------
    path : path-like
        Its ending (``.off``, ``.ply``, ``.obj``, any case) names the format.

    Returns
    -------
    Mesh
        In the file's own coordinates (see :func:`normalize_to_unit_box`).
    """
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(f"path: no such mesh file {path}", "path")
    if path.suffix.lower() == ".off":
        return read_off(path)
    if path.suffix.lower() not in (".ply", ".obj", ".stl", ".glb", ".gltf"):
        raise InvalidInputError(f"path: unsupported mesh format {path.suffix!r} (OFF, PLY, OBJ)", "path")
    import trimesh  # only needed for the formats the small OFF reader does not do

    tm = trimesh.load(path, force="mesh", process=False)
    return Mesh(np.asarray(tm.vertices, dtype=np.float64), np.asarray(tm.faces, dtype=np.int64))


def normalize_to_unit_box(mesh: Mesh, size: float = 1.0) -> Mesh:
    """Centre the bounding box at the origin and scale its longest side to ``size``.

    With the default the mesh fits the unit box [-1/2, 1/2]^3, the aspect
    ratio kept.

    Parameters
    ----------
    mesh : Mesh
    size : float
        Length of the longest side afterwards.
    """
    lo, hi = mesh.bounds
    extent = float((hi - lo).max())
    if not extent > 0:
        raise InvalidInputError("mesh: all vertices coincide; cannot normalise", "mesh")
    v = (mesh.vertices - (lo + hi) / 2) * (size / extent)
    return Mesh(v, mesh.faces)


def default_cache_dir() -> Path:
    """``$FLATSERVE_CACHE`` or ``$XDG_CACHE_HOME/flatserve`` (``~/.cache/flatserve``)."""
    env = os.environ.get("FLATSERVE_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "flatserve"


def bunny_path(cache_dir: str | os.PathLike | None = None, tarball: str | os.PathLike = CGAL_DATA_TARBALL) -> Path:
    """Path of the bunny OFF file, extracted from Debian's CGAL data on first use.

    Parameters
    ----------
    cache_dir : path-like, optional
        Where to keep the extracted file (default :func:`default_cache_dir`).
    tarball : path-like
        The ``libcgal-demo`` data archive.

    Raises
    ------
    FileNotFoundError
        If the archive is missing (install Debian's ``libcgal-demo``:
        ``scripts/install-system-deps.sh``).
    """
    cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    out = cache / "meshes" / Path(BUNNY_MEMBER).name
    if out.is_file():
        return out
    tarball = Path(tarball)
    if not tarball.is_file():
        raise FileNotFoundError(
            f"{tarball} not found: the bunny comes from Debian's libcgal-demo package "
            "(run scripts/install-system-deps.sh)"
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    with tarfile.open(tarball, "r:gz") as tf:
        member = tf.extractfile(BUNNY_MEMBER)
        if member is None:
            raise FileNotFoundError(f"{BUNNY_MEMBER} not in {tarball}")
        tmp = out.with_suffix(f".tmp{os.getpid()}")
        tmp.write_bytes(member.read())
        os.replace(tmp, out)  # atomic: concurrent first uses do not see half a file
    return out


def load_bunny(cache_dir: str | os.PathLike | None = None) -> Mesh:
    """The Stanford bunny (``bunny00.off``) normalised into the unit box.

    The file's bunny stands along +y; it is turned by 180° about y so that
    eyes at negative z (the paper's set-up) see its classic profile, head to
    the right.
    """
    mesh = normalize_to_unit_box(read_off(bunny_path(cache_dir)))
    turn = np.diag([-1.0, 1.0, -1.0])  # 180 degrees about y
    return Mesh(mesh.vertices @ turn.T, mesh.faces)


def box_mesh(lo=(-0.5, -0.5, -0.5), hi=(0.5, 0.5, 0.5)) -> Mesh:
    """Axis-aligned box as 12 outward-facing triangles.

    Parameters
    ----------
    lo, hi : (3,) float
        Opposite corners.
    """
    lo = as_array(lo, "lo", (3,))
    hi = as_array(hi, "hi", (3,))
    corners = np.array([[(hi if (i >> a) & 1 else lo)[a] for a in range(3)] for i in range(8)])
    # quads as corner bit patterns, counter-clockwise seen from outside
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    faces = [(q[0], q[1], q[2]) for q in quads] + [(q[0], q[2], q[3]) for q in quads]
    return Mesh(corners, np.asarray(faces, dtype=np.int64))


def icosphere(subdivisions: int = 2, radius: float = 1.0, center=(0.0, 0.0, 0.0)) -> Mesh:
    """Sphere approximated by a subdivided icosahedron (vertices on the sphere).

    Parameters
    ----------
    subdivisions : int
        Each step splits every triangle into four (20 * 4**s faces).
    radius : float
    center : (3,) float
    """
    t = (1 + 5**0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t),
         (0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
         (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
         (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.asarray(p, float) / np.linalg.norm(p) for p in v]
    faces = list(f)
    for _ in range(int(subdivisions)):
        mid: dict[tuple[int, int], int] = {}

        def midpoint(i, j):
            key = (min(i, j), max(i, j))
            if key not in mid:
                p = verts[i] + verts[j]
                verts.append(p / np.linalg.norm(p))
                mid[key] = len(verts) - 1
            return mid[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    center = as_array(center, "center", (3,))
    return Mesh(np.asarray(verts) * radius + center, np.asarray(faces, dtype=np.int64))


def merge_meshes(*meshes: Mesh, transforms=None) -> Mesh:
    """One mesh holding the triangles of several (each optionally moved first).

    Parameters
    ----------
    *meshes : Mesh
    transforms : sequence of (R (3, 3), t (3,)) or None, optional
        Per mesh, vertices become ``v @ R.T + t`` (None: unchanged).

    Returns
    -------
    Mesh
        Vertices and faces concatenated (faces re-indexed); overlapping
        parts stay as they are (ray casting takes the first hit).
    """
    if not meshes:
        raise InvalidInputError("meshes: expected at least one mesh", "meshes")
    transforms = [None] * len(meshes) if transforms is None else list(transforms)
    if len(transforms) != len(meshes):
        raise InvalidInputError(f"transforms: expected one per mesh ({len(meshes)}), got "
                                f"{len(transforms)}", "transforms")
    vs, fs, off = [], [], 0
    for m, tr in zip(meshes, transforms):
        v = m.vertices
        if tr is not None:
            R = as_array(tr[0], "transforms", (3, 3))
            t = as_array(tr[1], "transforms", (3,))
            v = v @ R.T + t
        vs.append(v)
        fs.append(m.faces + off)
        off += v.shape[0]
    return Mesh(np.concatenate(vs), np.concatenate(fs))
