"""The composite's truth on a scene folder (issue 44): ``python -m bench.composite.photo_truth [SCENE] [--spp N]``
path-traces the first photo's view with the Lambert object in the room and without it
(:func:`pipeline.scene.make_scene.photo_references`; make-scene writes the same files for a new scene)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from pipeline.scene.make_scene import photo_references


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", nargs="?", default="data_samples")
    ap.add_argument("--spp", type=int, default=1024)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    print(json.dumps(photo_references(Path(a.scene), a.spp, a.seed), indent=1))


if __name__ == "__main__":
    main()
