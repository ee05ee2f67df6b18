"""All file reading and writing of pcrelight, one submodule by what it reads:

- :mod:`.common` — atomic writes (:func:`atomic_path`), the ``<file>: <problem>`` checks, file references
  (SHA-256), JSON (reports; scene.json and its checks);
- :mod:`.clouds` — point clouds: the pipeline's PLY (:class:`Cloud`, :func:`read_cloud`, :func:`write_cloud`)
  and the scans users bring, by suffix (:data:`CLOUD_READERS`, :func:`read_scan`);
- :mod:`.images` — EXR / Radiance HDR / PNG (OpenImageIO), previews, figures;
- :mod:`.npz` — stage files (NPZ with a schema from :mod:`pipeline.schemas`);
- :mod:`.meshes` — triangle meshes and renderable objects (PLY / OBJ / glTF through trimesh, the glTF JSON
  for what trimesh drops).

Every public name is re-exported here: ``from pipeline import io; io.read_cloud(...)``. Every writer is
atomic: it writes a temp file in the target folder, fsyncs it and renames it over the target, so an
interrupted stage leaves the previous output intact. Every reader turns a bad file into
:class:`~pipeline.errors.InputError` (``<file>: <problem>``).
"""

from __future__ import annotations

from ..color import luminance, srgb_decode, srgb_encode  # noqa: F401  (re-exported: io.luminance etc. are used widely)
from .clouds import (
    CLOUD_READERS, PCD_DATA, Cloud, Scan, check_pcd_header, estimate_normals, read_cloud, read_e57_scan,
    read_gaussian_splats, read_las_scan, read_open3d_scan, read_ply_scan, read_scan, scan_point_count, scan_reader,
    write_cloud, write_gaussian_splats,
)
from .common import (
    PathLike, atomic_path, file_ref, first_line, follow_ref, must_exist, os_problem, read_json, read_scene,
    sha256_of, validate_scene, write_json,
)
from .images import (
    MAX_IMAGE_VALUES, image_attributes, image_channels, read_image, save_figure, write_image, write_png,
    write_preview,
)
from .meshes import (
    GLTF_IGNORED_EXTENSIONS, check_materials, read_mesh, read_object, texture_transform, uv_transformed, write_mesh,
)
from .npz import check_arrays, read_npz, write_npz  # noqa: F401
