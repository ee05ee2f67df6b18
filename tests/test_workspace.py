"""pipeline/io/workspace.py: the artifact paths and the face folders (write/read, checked channels and sizes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline import io
from pipeline.errors import InputError
from pipeline.io.workspace import FaceFolder, Workspace, read_face, read_faces, report_of, write_faces


def test_face_folder_layout(tmp_path):
    ff = FaceFolder(tmp_path / "cubemaps")
    assert ff.face(7) == tmp_path / "cubemaps" / "face_007.exr"
    assert (ff.cameras.name, ff.renderings.name, ff.report.name) == ("cameras.npz", "renderings.npz", "report.json")


def test_write_and_read_faces_round_trip_with_named_channels(tmp_path):
    rng = np.random.default_rng(0)
    faces = rng.random((3, 8, 10, 5)).astype(np.float32)
    write_faces(tmp_path, faces, 6, ["R", "G", "B", "A", "Z"])
    assert sorted(p.name for p in FaceFolder(tmp_path).stored_faces()) == ["face_006.exr", "face_007.exr", "face_008.exr"]
    got = read_face(tmp_path, 7, ["Z", "A"], size=(10, 8))
    assert got.dtype == np.float32 and np.array_equal(got, faces[1][..., [4, 3]])
    with pytest.raises(InputError, match=r"face_006.exr: missing channel\(s\) Q \(has R,G,B,A,Z\)"):
        read_face(tmp_path, 6, ["R", "Q"])
    with pytest.raises(InputError, match=r"face_006.exr: size 10x8 != 8x8"):
        read_face(tmp_path, 6, ["R"], size=(8, 8))


def _cameras(n: int, w: int, h: int) -> dict[str, np.ndarray]:
    return dict(K=np.tile(np.eye(3), (n, 1, 1)), world_to_camera=np.tile(np.eye(4), (n, 1, 1)),
                resolution=np.tile(np.int32([w, h]), (n, 1)), view=np.zeros(n, np.int32),
                face=np.arange(n, dtype=np.int32), eye=np.zeros((1, 3)))


def test_read_faces_pairs_the_rendered_and_the_expanded_faces(tmp_path):
    cub, hdr = FaceFolder(tmp_path / "c"), FaceFolder(tmp_path / "h")
    rng = np.random.default_rng(1)
    a = rng.random((2, 4, 6, 5)).astype(np.float32)
    b = rng.random((2, 4, 6, 4)).astype(np.float32)
    write_faces(cub, a, 0, ["R", "G", "B", "A", "Z"])
    write_faces(hdr, b, 0, ["R", "G", "B", "Q"])
    io.write_npz(cub.cameras, "pcrelight.cameras/1", **_cameras(2, 6, 4))
    rend = dict(method=np.asarray("pmatch"), scale=np.float64(1), count=np.int32(2), q_norm=np.asarray("x"),
                matched_fraction=np.zeros(2), max_luminance=np.float64(0))
    io.write_npz(hdr.renderings, "pcrelight.renderings/1", **rend)
    cams, r, depth, cover, col, qual = read_faces(cub, hdr.path)
    assert int(r["count"]) == 2 and len(cams["K"]) == 2
    assert np.array_equal(depth[1], a[1, ..., 4]) and np.array_equal(cover[0], a[0, ..., 3])
    assert np.array_equal(col[1], b[1, ..., :3]) and np.array_equal(qual[0], b[0, ..., 3])
    io.write_npz(hdr.renderings, "pcrelight.renderings/1", **{**rend, "count": np.int32(3)})
    with pytest.raises(InputError, match="renderings.npz: count 3 != 2 faces"):
        read_faces(cub, hdr)


def test_workspace_paths_and_renaming(tmp_path):
    ws = Workspace(tmp_path / "in", tmp_path / "ws")
    assert ws.photo == tmp_path / "in" / "photo.exr" and ws.object == tmp_path / "in" / "object.glb"
    assert ws.cubemaps.cameras == tmp_path / "ws" / "cubemaps" / "cameras.npz"
    assert ws.relit == tmp_path / "ws" / "relit.png" and ws.relit_stats == tmp_path / "ws" / "stats.json"
    assert ws.exposure_report.name == "exposure.json" and ws.exposure_fit.name == "exposure_fit.png"
    assert report_of(ws.cloud_hdr) == tmp_path / "ws" / "cloud_hdr.json"
    assert ws.preview("bsh") == tmp_path / "ws" / "bsh.png"
    assert Workspace(tmp_path, tmp_path, previews=False).preview("bsh") is None
    assert Workspace(tmp_path, tmp_path, object_file=Path("x.obj")).object == Path("x.obj")
    m = ws.renamed(hdr_faces="faces_rhee", cloud_hdr="cloud_rhee.ply")
    assert m.hdr_faces.path == tmp_path / "ws" / "faces_rhee" and m.cloud_hdr.name == "cloud_rhee.ply"
    assert m.cubemaps.path == ws.cubemaps.path and ws.hdr_faces.path.name == "hdr_faces"
    with pytest.raises(ValueError, match="unknown artifact"):
        ws.renamed(nope="x")
