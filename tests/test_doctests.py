"""The examples in the public entry points' docstrings run and print what they show (pytest does not collect
doctests by itself: ``testpaths`` is ``tests``)."""

from __future__ import annotations

import doctest
import importlib

import pytest

MODULES = ["parksim.camera.base", "parksim.camera.models", "parksim.geometry", "parksim.gaussians",
           "parksim.render.rasterize", "parksim.ipm", "parksim.data.layout", "parksim.frames", "parksim.env",
           "parksim.vehicle", "parksim.planners.geometric", "parksim.recon.config", "parksim.scenarios.task"]
"""Modules whose docstrings carry examples: ``CameraModel.project``/``unproject``, ``rasterize``, ``IPM``, poses,
``pixel_grid``, the lens models, the npz format, the vehicle's collision test, Dubins paths, configs, the parking
task's heading error."""


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0, f"{name} has no docstring examples"
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples in {name} failed (output above)"
