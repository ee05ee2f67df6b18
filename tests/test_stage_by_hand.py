"""The stage commands as README writes them give what ``pcrelight run`` gives.

README's "whole chain by hand" block (the stage verbs of ``configs/demo.toml``, each with its options) is
run line by line on the tiny scene, in one folder; ``pcrelight run`` runs ``configs/demo.toml`` on the same
inputs in another. Both get the same smaller sizes (cube faces 64 px, 3 PatchMatch iterations, a 48×48
relight) so that the test is short; nothing else is added to README's lines. Every data file both write
(NPZ, EXR, PLY, PNG) must be byte-identical (run's plan skips the cube maps and PatchMatch, which the registered
photo makes unnecessary: they reach no byte of the cloud); the JSON reports differ only in paths and timings
and are not compared.
"""

from __future__ import annotations

import re
import shlex
import tomllib
from pathlib import Path

import numpy as np

from pipeline import io

ROOT = Path(__file__).resolve().parents[1]

# The same smaller sizes for `run` (its TOML tables) and for README's lines (options appended to the verb).
SMALL = {"render-cubemaps": {"size": 64}, "patchmatch": {"iterations": 3},
         "relight": {"size": "48x48", "microbuffer": 16}}

# The data files the chain writes, relative to the workspace (face folders: every face and the NPZ).
DATA = ["exposure.npz", "photo_ldr.exr", "cubemaps", "hdr_faces", "cloud_proj.ply", "cloud_hdr.ply", "bsh.npz",
        "relit.exr", "relit.png"]


def readme_chain() -> list[list[str]]:
    """README's by-hand chain: one argument list per command (without the leading ``pcrelight``)."""
    text = (ROOT / "README.md").read_text()
    at = text.index("The whole chain by hand")
    block = re.search(r"```sh\n(.*?)```", text[at:], re.S)
    assert block, "README: no sh block after 'The whole chain by hand'"
    lines = block.group(1).replace("\\\n", " ").splitlines()
    cmds = [shlex.split(ln) for ln in lines if ln.strip()]
    assert cmds and all(c[0] == "pcrelight" for c in cmds)
    return [c[1:] for c in cmds]


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    return repr(v)


def _demo_toml(inputs: Path, workspace: Path) -> str:
    """configs/demo.toml with the inputs and workspace given and the SMALL sizes."""
    data = tomllib.loads((ROOT / "configs" / "demo.toml").read_text())
    data["run"].update(inputs=str(inputs), workspace=str(workspace))
    for verb, opts in SMALL.items():
        data.setdefault(verb, {}).update(opts)
    out = [f"seed = {data.pop('seed')}"]
    for table, kv in data.items():
        out.append(f"[{table}]")
        out += [f"{k} = {_toml_value(v)}" for k, v in kv.items()]
    return "\n".join(out) + "\n"


def _data_files(root: Path, skipped: tuple[str, ...] = ()) -> dict[str, bytes]:
    files: dict[str, bytes] = {}
    for name in DATA:
        p = root / name
        if name in skipped:
            assert not p.exists(), p
            continue
        assert p.exists(), p
        for f in ([p] if p.is_file() else sorted(q for q in p.iterdir() if q.suffix in (".exr", ".npz"))):
            files[str(f.relative_to(root))] = f.read_bytes()
    return files


def test_readme_chain_by_hand_is_run_byte_for_byte(tiny_scene, tmp_path, cli_run):
    hand, ws = tmp_path / "hand", tmp_path / "ws"
    cfg = tmp_path / "demo.toml"
    cfg.write_text(_demo_toml(tiny_scene, ws))
    code, _, err = cli_run("run", cfg)
    assert code == 0, err

    verbs = []
    for args in readme_chain():
        args = [a.replace("data_samples/", f"{tiny_scene}/").replace("out/hand", str(hand)) for a in args]
        for k, v in SMALL.get(args[0], {}).items():
            args += [f"--{k.replace('_', '-')}", str(v)]
        code, _, err = cli_run(*args)
        assert code == 0, (args, err)
        verbs.append(args[0])
    assert verbs == ["expose-match", "render-cubemaps", "patchmatch", "reproject", "poisson", "build-bsh", "relight"]

    # run's plan skips the cube maps and PatchMatch (the photo is registered, --unseen poisson: they reach no byte
    # of the cloud, pipeline/run/plan.py); the chain by hand runs them, and every file both write is the same bytes
    ran = io.read_json(ws / "run.json")["stages"]
    assert ran["render-cubemaps"]["skipped"] and "the photo is registered" in ran["patchmatch"]["plan"]
    got, want = _data_files(hand), _data_files(ws, skipped=("cubemaps", "hdr_faces"))
    assert sorted(k for k in got if not k.startswith(("cubemaps/", "hdr_faces/"))) == sorted(want)
    assert len([k for k in got if k.startswith("hdr_faces/face_")]) > 0
    differ = [k for k in want if got[k] != want[k]]
    assert not differ, differ
    # the chain is the registered-photo path: patchmatch recorded what it read, reproject took it from there
    rend = io.read_npz(hand / "hdr_faces" / "renderings.npz", "pcrelight.renderings/1")
    assert "photo_world_to_camera" in io.read_npz(hand / "exposure.npz", "pcrelight.exposure/1")
    assert (hand / "hdr_faces" / str(rend["photo"])).resolve() == (tiny_scene / "photo.exr").resolve()
    assert (hand / "hdr_faces" / str(rend["exposure"])).resolve() == (hand / "exposure.npz").resolve()
    rep = io.read_json(hand / "cloud_proj.json")
    assert Path(rep["photo"]).resolve() == (tiny_scene / "photo.exr").resolve()
    assert Path(rep["exposure"]).resolve() == (hand / "exposure.npz").resolve()


def _error_line(err: str) -> str:
    """The one error line (the log lines before it start with a time)."""
    lines = [ln for ln in err.splitlines() if ln.startswith("pcrelight: ")]
    assert len(lines) == 1 and err.rstrip("\n").splitlines()[-1] == lines[0], err
    return lines[0]


def test_reproject_refuses_in_one_line_when_patchmatch_inputs_are_gone_or_changed(tiny_scene, tmp_path, cli_run):
    import shutil

    w = tmp_path / "w"
    photo = tmp_path / "photo.exr"
    shutil.copy(tiny_scene / "photo.exr", photo)
    for args in (["expose-match", photo, tiny_scene / "cloud_ldr.ply", "--out", w / "e.npz", "--photo-ldr", w / "l.exr"],
                 ["render-cubemaps", tiny_scene / "cloud_ldr.ply", "--size", "32", "--out", w / "cm"],
                 ["patchmatch", w / "cm", "--photo", photo, "--photo-ldr", w / "l.exr", "--exposure", w / "e.npz",
                  "--iterations", "1", "--levels", "1", "--out", w / "hf"]):
        code, _, err = cli_run(*args)
        assert code == 0, err
    rp = ["reproject", tiny_scene / "cloud_ldr.ply", w / "cm", w / "hf"]
    code, _, err = cli_run(*rp, "--out", w / "a.ply")
    assert code == 0, err
    assert Path(io.read_json(w / "a.json")["photo"]).resolve() == photo.resolve()

    img = io.read_image(photo)
    io.write_image(photo, img * np.float32(2.0))          # the photo changed after patchmatch read it
    code, _, err = cli_run(*rp, "--out", w / "b.ply")
    assert code == 1 and not (w / "b.ply").exists()
    assert _error_line(err).startswith(f"pcrelight: {photo}: changed since it was read"), err
    code, _, err = cli_run(*rp, "--out", w / "c.ply", "--photo", photo)   # given on the command line: used, warned
    assert code == 0 and "is not the photo patchmatch read" in err, err

    photo.unlink()                                        # gone
    code, _, err = cli_run(*rp, "--out", w / "d.ply")
    assert code == 1 and not (w / "d.ply").exists()
    assert _error_line(err).startswith(f"pcrelight: {photo}: no such file"), err
