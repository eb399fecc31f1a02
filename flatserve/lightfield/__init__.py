"""Light fields: the paper's application (Sec. 5.2, Fig. 11).

Scenes from meshes (CGAL AABB-tree ray casting, diffuse shading), the paper's
random ray sampling, pinhole cameras, rendering novel views from a
:class:`flatserve.Field`, quality metrics and baselines.

>>> from flatserve.lightfield import Camera, bunny_scene, sample_scene, build_field, render_field
>>> scene = bunny_scene()                                   # doctest: +SKIP
>>> samples, values = sample_scene(scene, 200, seed=0)      # doctest: +SKIP
>>> field, stats = build_field(samples.origins, samples.directions, values)  # doctest: +SKIP
>>> frame = render_field(field, Camera(focal=4))            # doctest: +SKIP
"""
from .camera import RIGID_TOL, Camera, PinholeCamera, RaySamples, paper_samples, rotation_about
from .capture import (BATCH_RAYS, Capture, CaptureError, CaptureFrame, RayBatch, capture_batches, capture_rays,
                      field_options, read_capture, write_colmap, write_nerf)
from .mesh import Mesh, box_mesh, bunny_path, icosphere, load_bunny, load_mesh, normalize_to_unit_box
from .quality import psnr, ssim
from .render import Frame, render_field, render_truth
from .sampling import build_field, bunny_scene, sample_scene
from .scene import RayHits, Scene

__all__ = [
    "Camera", "RaySamples", "paper_samples", "rotation_about", "PinholeCamera", "RIGID_TOL",
    "BATCH_RAYS", "Capture", "CaptureError", "CaptureFrame", "RayBatch", "capture_batches", "capture_rays",
    "field_options", "read_capture", "write_colmap", "write_nerf",
    "Mesh", "box_mesh", "bunny_path", "icosphere", "load_bunny", "load_mesh", "normalize_to_unit_box",
    "psnr", "ssim", "Frame", "render_field", "render_truth",
    "build_field", "bunny_scene", "sample_scene",
    "RayHits", "Scene",
]
