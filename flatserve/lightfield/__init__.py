"""Light fields: the paper's application (Sec. 5.2, Fig. 11).

Scenes from meshes (CGAL AABB-tree ray casting, diffuse shading), the paper's
random ray sampling, pinhole cameras, rendering novel views from a
:class:`flatserve.Field`, quality metrics and baselines.
"""
from .camera import Camera, RaySamples, paper_samples, rotation_about
from .mesh import Mesh, box_mesh, bunny_path, icosphere, load_bunny, load_mesh, normalize_to_unit_box
from .scene import RayHits, Scene

__all__ = [
    "Camera", "RaySamples", "paper_samples", "rotation_about",
    "Mesh", "box_mesh", "bunny_path", "icosphere", "load_bunny", "load_mesh", "normalize_to_unit_box",
    "RayHits", "Scene",
]
