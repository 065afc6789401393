"""Finite but absurd Gaussians: dropped on load with a count per reason, never widening the pose bounds.

Every bundle here is a real folder written by ``parksim.bundle.save``: a small garage bundle (``make_bundle``) plus
Gaussians copied from it with one absurd value, read back through ``parksim.bundle.load``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient

import parksim.bundle as bundle_io
from parksim.bundle import Bundle, BundleError, absurd_gaussians
from parksim.frames import RequestError
from parksim.gaussians import GaussianScene
from parksim.ply_3dgs import bundle_from_ply
from parksim.server import Settings, create_app
from parksim.server.scenes import check_pose
from parksim.server.schemas import Pose
from parksim.sim import LocalSim
from parksim.visibility import VisibilityGrid
from sim_fixtures import make_bundle

N = 300
FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh")
POSE = (12.0, 0.0, 0.1)
"""Inside the tiny garage (x 0..34, y -8.7..8.7), facing along it."""
ABSURD = {   # case: (field, value of the copied Gaussian, the reason load gives)
    "raw scale 1e30": ("log_scales", [math.log(1e30), 0.0, 0.0], "scale"),
    "log-scale 1e30": ("log_scales", [1e30, 0.0, 0.0], "scale"),
    "opacity logit 1e30": ("opacity_logits", 1e30, "opacity"),
    "mean at 1e30": ("means", [1e30, 0.0, 0.0], "mean"),
}


@pytest.fixture(scope="module")
def clean(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A normal bundle (map.json included) of N Gaussians, small cameras."""
    return make_bundle(tmp_path_factory.mktemp("clean") / "tiny", n=N, size=(64, 48), bev_px=64)


def _with_absurd(scene: GaussianScene, field: str, value: object, at: Sequence[int]) -> GaussianScene:
    """``scene`` with copies of its Gaussian 0 inserted so they sit at indices ``at``, ``field`` set to ``value``."""
    extra = scene.subset(torch.zeros(len(at), dtype=torch.long))
    bad = getattr(extra, field).clone()
    bad[:] = torch.tensor(value, dtype=bad.dtype)
    extra = GaussianScene(**{f: bad if f == field else getattr(extra, f) for f in FIELDS}, sh_degree=scene.sh_degree)
    joined = GaussianScene(**{f: torch.cat([getattr(scene, f), getattr(extra, f)]) for f in FIELDS},
                           sh_degree=scene.sh_degree)
    order = list(range(len(scene)))
    for j, i in enumerate(sorted(at)):
        order.insert(i, len(scene) + j)
    return joined.subset(torch.tensor(order))


def _save(clean: Path, out: Path, scene: GaussianScene, with_map: bool = True,
          visibility: VisibilityGrid | None = None) -> Path:
    """A bundle folder like ``clean`` holding ``scene`` (without map.json unless ``with_map``)."""
    b = bundle_io.load(clean)
    return bundle_io.save(out, Bundle(scene, b.rig, b.map if with_map else None, b.meta, visibility))


def _same_scene(a: GaussianScene, b: GaussianScene) -> None:
    assert len(a) == len(b) and a.sh_degree == b.sh_degree
    for f in FIELDS:
        assert torch.equal(getattr(a, f), getattr(b, f)), f


def _same_frames(a: LocalSim, b: LocalSim) -> None:
    """Every view, depth map and BEV at POSE are bit-identical."""
    fa, fb = (s.render(POSE, bev=True, depth=True) for s in (a, b))
    for name in a.cameras:
        assert np.array_equal(fa.images[name], fb.images[name]), name
        assert np.array_equal(fa.depth[name], fb.depth[name]), name
    assert np.array_equal(fa.bev, fb.bev)


@pytest.mark.parametrize("case", list(ABSURD))
def test_one_absurd_gaussian_is_dropped_and_the_render_is_the_clean_one(clean: Path, tmp_path: Path, case: str,
                                                                        caplog: pytest.LogCaptureFixture) -> None:
    field, value, reason = ABSURD[case]
    clean_bundle = bundle_io.load(clean)
    assert clean_bundle.dropped == {}
    folder = _save(clean, tmp_path / "b", _with_absurd(clean_bundle.scene, field, value, [N // 2]))
    with caplog.at_level(logging.WARNING, logger="parksim.bundle"):
        loaded = bundle_io.load(folder)
    assert loaded.dropped == {reason: 1}
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and f"dropped 1 of {N + 1} absurd Gaussian(s): 1 with" in warnings[0], warnings
    _same_scene(loaded.scene, clean_bundle.scene)
    _same_frames(LocalSim(loaded), LocalSim(clean_bundle))


def test_outliers_without_a_map_do_not_widen_the_pose_bounds(clean: Path, tmp_path: Path) -> None:
    """A few means at 1e30 (2 %) and no map.json: the bounds are the clean scene's and pose=1e29,0,0 is refused."""
    scene = bundle_io.load(clean).scene
    outliers = _with_absurd(scene, "means", [1e30, 0.0, 0.0], [10, 100, 150, 200, 250, 299])
    reference = LocalSim(_save(clean, tmp_path / "clean", scene, with_map=False))
    folder = _save(clean, tmp_path / "scenes" / "outliers", outliers, with_map=False)
    sim = LocalSim(folder)
    assert sim.bundle.dropped == {"mean": 6}
    assert sim.bounds == reference.bounds and sim.bounds["x"][1] < 40
    # A bundle built in memory (never loaded) keeps its outliers; its bounds still ignore them.
    kept = LocalSim(Bundle(outliers, sim.bundle.rig))
    assert len(kept.bundle.scene) == N + 6 and kept.bounds == reference.bounds
    for s in (sim, kept):
        with pytest.raises(RequestError, match=r"pose x=1e\+29 is outside scene"):
            check_pose(s, Pose(x=1e29, y=0.0, yaw=0.0), Settings())
    with TestClient(create_app(folder.parent, Settings())) as client:
        r = client.get("/render", params={"pose": "1e29,0,0", "cameras": "front"})
        info = client.get("/scenes/outliers").json()
    assert r.status_code == 422 and "x must be in" in r.json()["detail"], r.text
    assert info["dropped"] == {"mean": 6} and info["gaussians"] == N


def test_a_scene_of_absurd_gaussians_is_refused_in_one_line(clean: Path, tmp_path: Path) -> None:
    scene = bundle_io.load(clean).scene
    every = GaussianScene(**{f: getattr(scene, f) for f in FIELDS if f != "opacity_logits"},
                          opacity_logits=torch.full((N,), 1e30), sh_degree=scene.sh_degree)
    with pytest.raises(BundleError) as refused:
        bundle_io.load(_save(clean, tmp_path / "all", every))
    message = str(refused.value)
    assert "\n" not in message and f"{N} of {N} Gaussians are absurd" in message and "none is usable" in message
    many = _with_absurd(scene, "log_scales", [1e30, 0.0, 0.0], list(range(0, N, 4)))   # 75 of 375: 20 %
    with pytest.raises(BundleError, match=r"75 of 375 Gaussians are absurd \(75 with largest scale above 20x.*"
                                          r"more than 10%"):
        bundle_io.load(_save(clean, tmp_path / "many", many))


def test_the_garage_box_is_never_tighter_than_the_scene(clean: Path) -> None:
    """Gaussians huddled in 1 m, one more at the garage's far end: kept with the map, dropped without it."""
    b = bundle_io.load(clean)
    huddle = GaussianScene.random(50, bounds=((0, -0.5, 0), (1, 0.5, 1)), seed=1)
    far = _with_absurd(huddle, "means", [33.0, 8.0, 2.5], [25])
    assert not any(mask.any() for mask in absurd_gaussians(far, b.map).values())
    assert absurd_gaussians(far)["mean"].nonzero()[0].tolist() == [25]


def test_a_visibility_grid_is_renumbered_with_the_dropped_gaussian(clean: Path, tmp_path: Path) -> None:
    """Two measured cells covering the garage; the absurd Gaussian is listed in both and is gone from both."""
    scene = bundle_io.load(clean).scene

    def grid(absurd: int | None) -> VisibilityGrid:
        """Cell 0 sees the clean scene's even Gaussians, cell 1 all; with ``absurd``, indices of the scene holding it
        there (later ones shifted by one) and it in both cells."""
        cells = [list(range(0, N, 2)), list(range(N))]
        if absurd is not None:
            cells = [sorted([i + (i >= absurd) for i in cell] + [absurd]) for cell in cells]
        return VisibilityGrid(0.0, -9.0, 18.0, 2, 1, np.cumsum([0] + [len(c) for c in cells]),
                              np.concatenate(cells).astype(np.int32), np.array([True, True]))

    at = 151
    loaded = bundle_io.load(_save(clean, tmp_path / "b", _with_absurd(scene, "opacity_logits", 1e30, [at]),
                                  visibility=grid(at)))
    reference = bundle_io.load(_save(clean, tmp_path / "clean", scene, visibility=grid(None)))
    assert loaded.dropped == {"opacity": 1} and loaded.visibility is not None and reference.visibility is not None
    for name in ("offsets", "indices", "measured"):
        assert np.array_equal(getattr(loaded.visibility, name), getattr(reference.visibility, name)), name
    _same_frames(LocalSim(loaded), LocalSim(reference))


def test_bundle_from_ply_drops_them_too(clean: Path, tmp_path: Path) -> None:
    scene = bundle_io.load(clean).scene
    scene.save_ply(tmp_path / "clean.ply")
    _with_absurd(scene, "log_scales", [math.log(1e30), 0.0, 0.0], [7]).save_ply(tmp_path / "absurd.ply")
    kwargs = {"rig": clean / "rig.json", "world_map": clean / "map.json"}
    written = bundle_from_ply(tmp_path / "absurd.ply", output=tmp_path / "absurd", **kwargs)
    reference = bundle_from_ply(tmp_path / "clean.ply", output=tmp_path / "clean", **kwargs)
    assert written.meta["ply_import"]["dropped"] == {"scale": 1} and reference.meta["ply_import"]["dropped"] == {}
    _same_scene(bundle_io.load(tmp_path / "absurd").scene, bundle_io.load(tmp_path / "clean").scene)
