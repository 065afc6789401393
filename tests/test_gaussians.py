"""GaussianScene: shapes, helpers and the INRIA 3DGS PLY round trip and error messages."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from parksim.gaussians import GaussianScene, PLYFormatError


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_ply_round_trip(tmp_path, degree):
    scene = GaussianScene.random(50, sh_degree=degree, seed=degree)
    path = tmp_path / "scene.ply"
    scene.save_ply(path)
    back = GaussianScene.load_ply(path)
    assert back.sh_degree == degree and len(back) == 50
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        torch.testing.assert_close(getattr(back, name), getattr(scene, name), rtol=0, atol=0)


def test_ply_layout_is_inria(tmp_path):
    """f_rest is channel-major (all of R, then G, then B) and the fields come in INRIA's order."""
    scene = GaussianScene.random(4, sh_degree=2, seed=1)
    path = tmp_path / "s.ply"
    scene.save_ply(path)
    v = PlyData.read(str(path))["vertex"]
    names = [p.name for p in v.properties]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[-8:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    k = 9
    sh = scene.sh.numpy()
    np.testing.assert_array_equal(v["f_rest_0"], sh[:, 1, 0])
    np.testing.assert_array_equal(v["f_rest_1"], sh[:, 2, 0])
    np.testing.assert_array_equal(v[f"f_rest_{k - 1}"], sh[:, 1, 1])
    np.testing.assert_array_equal(v["rot_0"], scene.quats[:, 0].numpy())


def _write(path, fields: dict[str, np.ndarray]) -> None:
    n = len(next(iter(fields.values())))
    data = np.empty(n, dtype=[(k, "f4") for k in fields])
    for k, col in fields.items():
        data[k] = col
    PlyData([PlyElement.describe(data, "vertex")]).write(str(path))


def _valid_fields(n: int = 3) -> dict[str, np.ndarray]:
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]
    return {k: np.ones(n, np.float32) for k in names}


def test_ply_without_normals_loads(tmp_path):
    _write(tmp_path / "a.ply", _valid_fields())
    assert GaussianScene.load_ply(tmp_path / "a.ply").sh_degree == 0


@pytest.mark.parametrize("field", ["opacity", "x", "rot_2", "f_dc_1"])
def test_ply_non_finite_is_rejected(tmp_path, field):
    fields = _valid_fields()
    fields[field][1] = np.nan if field != "x" else np.inf
    _write(tmp_path / "bad.ply", fields)
    with pytest.raises(PLYFormatError, match=rf"bad\.ply.*'{field}'.*vertex 1"):
        GaussianScene.load_ply(tmp_path / "bad.ply")


def test_ply_missing_field_is_rejected(tmp_path):
    fields = _valid_fields()
    del fields["scale_1"]
    _write(tmp_path / "m.ply", fields)
    with pytest.raises(PLYFormatError, match=r"m\.ply.*scale_1"):
        GaussianScene.load_ply(tmp_path / "m.ply")


def test_ply_bad_sh_count_is_rejected(tmp_path):
    fields = _valid_fields()
    fields.update({f"f_rest_{i}": np.zeros(3, np.float32) for i in range(5)})
    _write(tmp_path / "sh.ply", fields)
    with pytest.raises(PLYFormatError, match=r"sh\.ply.*f_rest"):
        GaussianScene.load_ply(tmp_path / "sh.ply")


def test_ply_garbage_and_missing_file(tmp_path):
    (tmp_path / "g.ply").write_bytes(b"this is not a ply file\n\x00\x01")
    with pytest.raises(PLYFormatError, match=r"g\.ply"):
        GaussianScene.load_ply(tmp_path / "g.ply")
    with pytest.raises(PLYFormatError, match="not found"):
        GaussianScene.load_ply(tmp_path / "nope.ply")


def test_helpers():
    scene = GaussianScene.random(10, bounds=((0, 0, 0), (1, 2, 3)), sh_degree=1, seed=3)
    assert len(scene) == 10 and scene.sh.shape == (10, 4, 3)
    assert (scene.means >= 0).all() and (scene.means <= torch.tensor([1.0, 2.0, 3.0])).all()
    colours = 0.28209479177387814 * scene.sh[:, 0] + 0.5
    assert ((colours >= 0) & (colours <= 1)).all()
    sub = scene.subset(scene.means[:, 0] > 0.5)
    assert len(sub) == int((scene.means[:, 0] > 0.5).sum())
    assert scene.to(torch.float64).means.dtype == torch.float64
    torch.testing.assert_close(GaussianScene.random(5, seed=7).means, GaussianScene.random(5, seed=7).means)


def test_shape_validation():
    scene = GaussianScene.random(4)
    with pytest.raises(ValueError, match="sh must have shape"):
        GaussianScene(scene.means, scene.quats, scene.log_scales, scene.opacity_logits, scene.sh, sh_degree=2)
    with pytest.raises(ValueError, match="quats"):
        GaussianScene(scene.means, scene.quats[:, :3], scene.log_scales, scene.opacity_logits, scene.sh, 0)


def test_spatially_sorted_is_a_permutation_that_groups_neighbours():
    scene = GaussianScene.random(4000, sh_degree=2, seed=5)
    ordered = scene.spatially_sorted()
    rows = lambda s: torch.cat([s.means, s.quats, s.log_scales, s.opacity_logits[:, None], s.sh.flatten(1)], 1)  # noqa: E731
    a, b = rows(scene), rows(ordered)
    assert torch.equal(a[torch.argsort(a[:, 0])], b[torch.argsort(b[:, 0])])
    step = lambda s: (s.means[1:] - s.means[:-1]).norm(dim=-1).median()  # noqa: E731
    assert step(ordered) < 0.2 * step(scene)             # consecutive rows are near in space
    assert len(GaussianScene.random(0).spatially_sorted()) == 0
