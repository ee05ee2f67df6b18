"""The one registry of NPZ schemas: every stage file's keys, dtypes and shapes.

Each entry maps a key to ``(dtype, shape)`` or ``(dtype, shape, "optional")``.
``dtype`` is a numpy dtype name (``"float32"``), ``"str"`` (a unicode scalar or array) or
``"void40"`` (a structured record of 40 bytes). ``shape`` is a tuple whose items are ints,
names (the same name must be the same size within one file) or ``None`` (any size).
The file's own ``schema`` key (e.g. ``"pcrelight.cameras/1"``) is checked against the name.
"""

from __future__ import annotations

Spec = dict[str, tuple]

SCHEMAS: dict[str, Spec] = {
    # render-cubemaps → patchmatch, reproject (DESIGN stage 2)
    "pcrelight.cameras/1": {
        "K": ("float64", ("F", 3, 3)),
        "world_to_camera": ("float64", ("F", 4, 4)),
        "resolution": ("int32", ("F", 2)),
        "view": ("int32", ("F",)),
        "face": ("int32", ("F",)),
        "eye": ("float64", ("V", 3)),
        # how the faces were splatted, so that reproject repeats the visibility test exactly
        "splat_k": ("int32", (), "optional"),          # splat radius = splat_scale × mean kNN distance
        "splat_scale": ("float64", (), "optional"),
        "backface_cull": ("int32", (), "optional"),    # 1: points facing away from the eye were not drawn
        "facing_test": ("int32", (), "optional"),      # 1: a point facing away from the eye is not seen
        "depth_tol": ("float64", (), "optional"),      # seen if d ≤ Z·(1+depth_tol) + radius_tol·r
        "radius_tol": ("float64", (), "optional"),
    },
    # expose-match → patchmatch, reproject (DESIGN stage 1): α of Eq. 1 and every tried value
    "pcrelight.exposure/1": {
        "alpha": ("float64", ()),            # photo_ldr = clamp(alpha * photo, 0, 1): the chosen estimate
        "alpha_histogram": ("float64", (), "optional"),   # Eq. 1's estimate
        "alpha_source": ("str", (), "optional"),          # "histogram" (Eq. 1) or "register"
        "alpha_register": ("float64", (), "optional"),    # from the registered photo's points (when registered)
        "register_ncc": ("float64", (), "optional"),
        "register_blocks": ("int32", (), "optional"),
        "photo_K": ("float64", (3, 3), "optional"),       # registered camera: OpenCV intrinsics [pixels]
        "photo_world_to_camera": ("float64", (4, 4), "optional"),  # ... and pose (world → OpenCV camera)
        # several photos, or a placed panorama/fisheye (issue 25; pipeline/expansion/photo_set.py): one entry per photo given
        "photos": ("str", ("P",), "optional"),                  # paths relative to exposure.npz's folder (io.file_ref)
        "photos_sha256": ("str", ("P",), "optional"),
        "photos_model": ("str", ("P",), "optional"),            # pinhole | equirect | fisheye (camera.MODELS)
        "photos_size": ("int32", ("P", 2), "optional"),         # width, height [pixels]
        "photos_world_to_camera": ("float64", ("P", 4, 4), "optional"),  # OpenCV axes
        "photos_K": ("float64", ("P", 3, 3), "optional"),       # pinhole intrinsics (zeros for the other models)
        "photos_fov_deg": ("float64", ("P",), "optional"),      # pinhole vertical / fisheye circle's field of view
        "photos_registered": ("uint8", ("P",), "optional"),     # 1: pose from registration; 0: placed (--photo-at)
        "photos_quality": ("float64", ("P",), "optional"),      # registration NCC (1 for a placed camera)
        "photos_kept": ("uint8", ("P",), "optional"),           # 0: dropped (not registered, or not confidently)
        "photos_scale": ("float64", ("P",), "optional"),        # k_i: photo i in cloud units = alpha * k_i * photo_i
        "photos_alpha_register": ("float64", ("P",), "optional"),  # each photo's own exposure (registration alone)
        "log2_alpha": ("float64", ()),
        "distance": ("float64", ()),         # Wasserstein distance of the luminance histograms at alpha
        "tried_log2_alpha": ("float64", ("T",)),
        "tried_distance": ("float64", ("T",)),
        "tried_phase": ("int32", ("T",)),    # 0 grid candidate, 1 bisection
        "cloud_hist": ("float64", ("B",)),
        "photo_hist": ("float64", ("B",)),   # of clamp(alpha * photo) on the same bins
        "hist_space": ("str", ()),           # "srgb" (CIE Y sRGB-encoded) or "linear"
        "iterations": ("int32", ()),
    },
    # patchmatch → reproject (DESIGN stage 3): beside face_{i:03d}.exr (R,G,B expanded HDR, Q quality)
    "pcrelight.renderings/1": {
        "method": ("str", ()),               # pmatch | landis | banterle | rhee
        "scale": ("float64", ()),            # R,G,B * scale = the cloud's units (alpha for pmatch, 1 for ITMOs)
        "count": ("int32", ()),              # number of faces
        "q_norm": ("str", (), "optional"),   # how Q is normalised (text)
        "matched_fraction": ("float64", ("F",), "optional"),  # per face: covered pixels with Q <= 1
        "max_luminance": ("float64", (), "optional"),         # the ITMOs' peak output [LDR units]
        "fit_fraction": ("float64", (), "optional"),          # pmatch: matched pixels with Q <= fit_q (photo fit)
        "fit_median_q": ("float64", (), "optional"),          # pmatch: median Q of the matched pixels
        "fit_ok": ("int32", (), "optional"),                  # pmatch: 1 = the photo fits the cloud's cube maps
        # the inputs patchmatch read, so that reproject run by hand uses the same ones (io.file_ref: the path
        # relative to the renderings folder and the file's SHA-256)
        "photo": ("str", (), "optional"),
        "photo_sha256": ("str", (), "optional"),
        "exposure": ("str", (), "optional"),
        "exposure_sha256": ("str", (), "optional"),
    },
    # build-bsh → relight (DESIGN stage 6, notes/contracts.md): M nodes in depth-first order, N points
    "pcrelight.bsh/1": {
        # "derived": build-bsh does not write these; the node records hold them and read_npz puts them back
        # (bsh_format.derived_arrays, the same bytes): a reader always has them
        "nodes": ("void40", ("M",)),          # right u4, skip u4, center 3f4, color 3f4, radius f4, cone u4 (RGBA8)
        "center": ("float32", ("M", 3), "derived"),  # [m]
        "radius": ("float32", ("M",), "derived"),    # [m]; contains the node's points and its children's spheres
        "splat_radius": ("float32", ("M",), "optional"),  # [m] the splat's radius ≤ radius (build_bsh.splat_radii); absent = radius
        "emitters": ("float32", ("E", 12), "optional"),  # isolated leaves and small bright objects gathered by Eq. 9 (build_bsh.split_emitters): centre [m], radius [m], normal, flat share, RGB, 0; absent = none
        "color": ("float32", ("M", 3), "derived"),  # linear radiance, mean of the node's points
        "cone_axis": ("float32", ("M", 3), "derived"),  # decoded (quantised, normalised) cone axis
        "cone_half_angle": ("float32", ("M",), "derived"),  # decoded, conservative (rounded up) [rad]
        "child": ("int32", ("M", 2), "derived"),  # (i+1, right) for inner nodes, (-1, -1) for leaves
        "first": ("int64", ("M",), "derived"),  # the node's points: order[first:first+count] (bsh_format.point_ranges)
        "count": ("int64", ("M",)),
        "order": ("int64", ("N",)),           # input point indices in Morton order
        "normal": ("float32", ("M", 3)),      # normalised sum of the node's unit normals (0 if they cancel)
        "depth": ("int32", ("M",), "derived"),  # root = 0
        "cluster": ("uint8", ("M",)),         # 1 = pruned sub-tree turned leaf
        "bbox_min": ("float64", (3,)),        # min corner of the cubed bounding box [m]; Morton cell k is centred on it + k voxels
        "cube_side": ("float64", ()),         # its side [m]
        "voxel_size": ("float64", ()),        # cube_side / 2**bits [m]
        "bits": ("int32", ()),
        "n_voxels": ("int64", ()),            # non-empty voxels = leaves before pruning
        "n_nodes_full": ("int64", ()),        # 2*n_voxels - 1, nodes before pruning
    },
    # make-scene → evaluate (truth/cloud_precise.npz): a subset of cloud_gt.ply's points re-baked to a target precision
    "pcrelight.cloud_precise/1": {
        "index": ("int64", ("P",)),                  # rows of cloud_gt.ply
        "colors": ("float64", ("P", 3)),             # outgoing radiance (linear Rec.709), independent of cloud_gt's
        "var": ("float64", ("P", 3)),                # variance of the mean
        "lum_var": ("float64", ("P",)),              # variance of the luminance mean
        "spp": ("int64", ("P",)),                    # paths each point got
    },
    # make-scene → expose-match / reproject tests, evaluate (truth/truth.npz)
    "pcrelight.truth/1": {
        "k": ("float64", ()),                        # photo = k × the cloud's radiance
        "e": ("float64", ()),                        # LDR cloud = clamp(e × HDR cloud) (Eq. 1)
        "alpha_true": ("float64", ()),               # e / k: clamp(alpha × photo) matches the LDR cloud
        "photo_K": ("float64", (3, 3), "optional"),  # OpenCV intrinsics (pixel centres at +0.5); pinhole photos only
        "photo_model": ("str", (), "optional"),      # camera.MODELS key; absent: pinhole (the panorama: equirect)
        "photo_world_to_camera": ("float64", (4, 4)),  # OpenCV camera: x right, y down, z forward
        "photo_size": ("int32", (2,)),               # width, height
        "photo_eye": ("float64", (3,)),
        "overexposed": ("uint8", ("N",)),            # LDR luminance > 0.9 or any channel = 255
        "photo_name": ("str", (), "optional"),       # the camera of scene.json "photos" this file describes
        "photo_visible": ("uint8", ("N",), "optional"),  # cloud points this photo sees (in frame, unoccluded)
    },
}


def register(name: str, spec: Spec) -> None:
    """Add a schema (used by tests that need a throw-away schema)."""
    SCHEMAS[name] = spec
