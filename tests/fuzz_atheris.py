"""Coverage-guided fuzzing of the readers with atheris (libFuzzer), for ``make fuzz``.

    python tests/fuzz_atheris.py READER [libFuzzer options, e.g. -max_total_time=60 -runs=100000]

READER: ply | exr | hdr | npz | obj | gltf | glb | toml | scene. Each input is written to a file with
that extension and read with pcrelight's reader; a clean InputError/ConfigError (one line) is the
expected answer to garbage, any other exception is a crash that atheris reports (with the input saved
as ``crash-*``). Seeds come from small valid files. The property tests in ``test_fuzz_readers.py`` are
the bounded version of this that ``make test`` runs.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import atheris

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

with atheris.instrument_imports(include=["pipeline"]):
    from pipeline import config, io
    from pipeline.errors import ConfigError, InputError

READERS = {
    "ply": (".ply", lambda p: io.read_cloud(p)),
    "exr": (".exr", lambda p: io.read_image(p)),
    "hdr": (".hdr", lambda p: io.read_image(p)),
    "npz": (".npz", lambda p: io.read_npz(p, "pcrelight.bsh/1")),
    "obj": (".obj", lambda p: io.read_object(p)),
    "gltf": (".gltf", lambda p: io.read_object(p)),
    "glb": (".glb", lambda p: io.read_object(p)),
    "toml": (".toml", lambda p: config.resolve(_relight_config(), p, "relight", {})),
    "scene": ("scene.json", lambda p: io.read_json(p)),
}


def _check(kind: str, res) -> None:
    """What a reader returned must be sound (a crash otherwise): images finite float32 (H, W, C), clouds
    valid with unit normals, object parts with finite positions and in-range materials."""
    import numpy as np

    if kind in ("exr", "hdr"):
        assert res.dtype == np.float32 and res.ndim == 3 and np.all(np.isfinite(res)), "image with NaN/Inf accepted"
    elif kind == "ply":
        res.validate("<fuzz>")
        assert np.all(np.abs(np.linalg.norm(res.normals, axis=1) - 1) < 1e-3), "normals are not unit length"
    elif kind in ("obj", "gltf", "glb"):
        for part in res:
            assert np.all(np.isfinite(part["positions"])), "non-finite positions accepted"
            assert np.all((part["base_color"] >= 0) & (part["base_color"] <= 1)), "base colour outside [0, 1]"
            assert 0 <= part["metallic"] <= 1 and 0 <= part["roughness"] <= 1, "metallic/roughness outside [0, 1]"


def _relight_config():
    from pipeline.relight.relight import RelightConfig

    return RelightConfig


def _seeds(kind: str, folder: Path) -> None:
    """Write a few valid inputs of ``kind`` into ``folder`` (the corpus libFuzzer starts from)."""
    import numpy as np

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    if kind == "ply":
        p = rng.normal(size=(6, 3)).astype(np.float32)
        io.write_cloud(folder / "a.ply", io.Cloud(p, (p / np.linalg.norm(p, axis=1, keepdims=True)).astype(np.float32),
                                                  rng.uniform(0, 1, (6, 3)).astype(np.float32)))
    elif kind in ("exr", "hdr"):
        io.write_image(folder / f"a.{kind}", rng.uniform(0, 2, (4, 5, 3)).astype(np.float32))
        if kind == "exr":  # half floats: a flipped exponent bit is an Inf or a NaN
            io.write_image(folder / "b.exr", rng.uniform(0, 2, (4, 5, 4)).astype(np.float32), half=True)
    elif kind == "npz":
        (folder / "a.npz").write_bytes(b"PK\x05\x06" + b"\0" * 18)
    elif kind in ("obj", "glb"):
        io.write_mesh(folder / f"a.{kind}", np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32))
    elif kind == "gltf":
        (folder / "a.gltf").write_text('{"asset": {"version": "2.0"}, "materials": [{"pbrMetallicRoughness": '
                                       '{"baseColorFactor": [0.5, 0.5, 0.5, 1]}}]}')
    elif kind == "toml":
        (folder / "a.toml").write_text('seed = 1\n[relight]\nalbedo = [0.5, 0.5, 0.5]\nfov = 40.0\n')
    elif kind == "scene":
        (folder / "scene.json").write_bytes((ROOT / "data_samples" / "scene.json").read_bytes())


def main() -> None:
    kind = sys.argv[1] if len(sys.argv) > 1 else ""
    if kind not in READERS:
        sys.exit(f"usage: {sys.argv[0]} {{{'|'.join(READERS)}}} [libFuzzer options]")
    suffix, read = READERS[kind]
    work = Path(tempfile.mkdtemp(prefix=f"pcrelight-fuzz-{kind}-"))
    target = work / ("scene.json" if kind == "scene" else f"input{suffix}")
    corpus = work / "corpus"
    _seeds(kind, corpus)

    def one_input(data: bytes) -> None:
        target.write_bytes(data)
        try:
            res = read(target)
        except (InputError, ConfigError) as e:
            if "\n" in str(e):
                raise AssertionError(f"multi-line error: {e!r}") from None
            return
        _check(kind, res)

    args = [sys.argv[0], *sys.argv[2:], str(corpus)]
    os.chdir(work)  # crash-* files land here
    print(f"fuzzing {kind}: work folder {work}", flush=True)
    atheris.Setup(args, one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
