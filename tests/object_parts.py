"""Test helper: two lists of object parts (io.read_object's dicts) equal key for key, type for type, byte for byte."""

from __future__ import annotations

import numpy as np


def assert_same_parts(got: list[dict], want: list[dict]) -> None:
    """``got`` holds the parts of ``want``: the same keys in the same order, the same types, arrays of the same dtype
    and bytes, other values equal."""
    assert len(got) == len(want)
    for g, w in zip(got, want):
        assert list(g) == list(w)
        for k in w:
            assert type(g[k]) is type(w[k]), k
            if isinstance(w[k], np.ndarray):
                assert g[k].dtype == w[k].dtype and g[k].tobytes() == w[k].tobytes(), k
            else:
                assert g[k] == w[k], k
