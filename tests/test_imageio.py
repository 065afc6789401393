"""to_uint8: rounding, clipping and NaN handling as a float64 reference, for every kind of input it gets."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from parksim.imageio import to_uint8


def _reference(arr: np.ndarray) -> np.ndarray:
    """round(clip(x, 0, 1) * 255) in float64, NaN -> 0."""
    x = np.clip(np.nan_to_num(np.asarray(arr, np.float64), nan=0.0), 0.0, 1.0)
    return np.floor(x * 255.0 + 0.5).astype(np.uint8)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_to_uint8_matches_the_reference_on_every_input_kind(dtype):
    rng = np.random.default_rng(0)
    x = rng.uniform(-0.5, 1.5, (30, 40, 3)).astype(dtype)
    x[0, :6, 0] = [np.nan, np.inf, -np.inf, 0.998, 0.5 / 255, 1.5 / 255]
    before = x.copy()
    read_only = x.copy()
    read_only.setflags(write=False)
    for image in (x, torch.from_numpy(x), x[..., 0], x[::2, ::-1], read_only):
        out = to_uint8(image)
        assert out.dtype == np.uint8 and out.shape == np.asarray(image).shape
        np.testing.assert_array_equal(out, _reference(np.asarray(image)))
    np.testing.assert_array_equal(x, before)                           # the input is left alone


def test_to_uint8_passes_uint8_through():
    u = np.arange(12, dtype=np.uint8).reshape(3, 4)
    for image in (u, torch.from_numpy(u)):
        out = to_uint8(image)
        assert out.dtype == np.uint8 and np.shares_memory(out, u) and np.array_equal(out, u)
