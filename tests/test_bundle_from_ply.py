"""Third-party 3DGS PLYs: SH rotation, world-frame conversion, and ``parksim bundle from-ply``."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from parksim import bundle as bundle_io
from parksim.cli import build_parser, main
from parksim.commands.bundle import read_transform
from parksim.env import ParkingEnv
from parksim.gaussians import GaussianScene
from parksim.geometry import quaternion_from_rotation, rotation_from_quaternion
from parksim.imageio import read_image, to_uint8
from parksim.ply_3dgs import FRAMES, T_parksim_ply, read_ply, similarity_parts, transform_scene, write_ply
from parksim.render import render
from parksim.render.sh import eval_sh, sh_basis
from parksim.sh_rotation import rotate_sh
from parksim.sim import LocalSim
from parksim.synth.presets import get_preset
from parksim.synth.rig import avm_rig
from sim_fixtures import garage_scene
from tolerances import f32_tol

ROTATION = rotation_from_quaternion(torch.tensor([0.3, -0.5, 0.7, 0.2], dtype=torch.float64)).numpy()


def _similarity(scale: float, Q: np.ndarray, t: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = scale * Q, t
    return T


SIMILARITY = _similarity(2.5, ROTATION, (3.0, -1.5, 0.25))
MIRROR = _similarity(0.4, ROTATION @ np.diag([1.0, -1.0, 1.0]), (-2.0, 0.5, 1.0))   # det < 0: a reflection
CASES = {"opengl": ("opengl", None), "opencv": ("opencv", None), "colmap": ("colmap", None),
         "opencv+similarity": ("opencv", SIMILARITY), "opengl+mirror": ("opengl", MIRROR)}


def _unit(n: int, seed: int) -> torch.Tensor:
    d = torch.randn(n, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    return d / d.norm(dim=1, keepdim=True)


def _radiance(sh: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """The SH sum before ``eval_sh``'s +0.5 and clamp: linear in the coefficients, so every one of them shows."""
    return torch.einsum("nk,nkc->nc", sh_basis(dirs, degree), sh)


@pytest.mark.parametrize("degree", [1, 2, 3])
@pytest.mark.parametrize("Q", [ROTATION, ROTATION @ np.diag([-1.0, 1.0, 1.0])], ids=["rotation", "reflection"])
def test_rotated_sh_shows_every_colour_in_the_rotated_direction(degree: int, Q: np.ndarray) -> None:
    """colour'(Q d) == colour(d) for directions the fit never saw, to float64 rounding at the colours' scale."""
    n = 500
    sh = torch.randn(n, (degree + 1) ** 2, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(degree))
    d = _unit(n, seed=7)
    turned = rotate_sh(sh, Q)
    before, after = _radiance(sh, d, degree), _radiance(turned, d @ torch.from_numpy(Q).T, degree)
    assert (after - before).abs().max() <= 64 * np.spacing(before.abs().max().item())
    assert (turned[:, 1:] - sh[:, 1:]).abs().max() > 0.1     # the coefficients did change


def _covariances(scene: GaussianScene) -> torch.Tensor:
    R = rotation_from_quaternion(scene.quats)
    return R @ torch.diag_embed(torch.exp(2 * scene.log_scales)) @ R.transpose(1, 2)


@pytest.mark.parametrize("T", [SIMILARITY, MIRROR], ids=["similarity", "mirror"])
def test_transform_scene_is_the_similarity_applied_to_each_gaussian(T: np.ndarray) -> None:
    """Against the definition, in float64: m' = s Q m + t, cov' = s^2 Q cov Q^T, colour'(Q d) = colour(d)."""
    scene = GaussianScene.random(300, sh_degree=3, seed=5, dtype=torch.float64)
    moved = transform_scene(scene, T)
    s, Q, t = (torch.as_tensor(v, dtype=torch.float64) for v in similarity_parts(T))
    want_means = s * scene.means @ Q.T + t
    assert (moved.means - want_means).abs().max() <= 16 * np.spacing(want_means.abs().max().item())
    want_cov = s**2 * Q @ _covariances(scene) @ Q.T
    assert (_covariances(moved) - want_cov).abs().max() <= 64 * np.spacing(want_cov.abs().max().item())
    assert torch.equal(moved.opacity_logits, scene.opacity_logits)
    d = _unit(len(scene), seed=3)
    before, after = _radiance(scene.sh, d, 3), _radiance(moved.sh, d @ Q.T, 3)
    assert (after - before).abs().max() <= 64 * np.spacing(before.abs().max().item())


def _scene_sh3(n: int = 3000) -> tuple[GaussianScene, dict]:
    """The tiny garage's surface Gaussians in float64 with random SH up to degree 3 (so view-dependent colour)."""
    scene, world_map = garage_scene("tiny", n)
    s = scene.to(torch.float64)
    rest = 0.3 * torch.randn(n, 15, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    return GaussianScene(s.means, s.quats, s.log_scales, s.opacity_logits, torch.cat([s.sh, rest], 1), 3), world_map


@pytest.fixture(scope="module")
def garage() -> tuple[GaussianScene, dict, object, tuple[float, float, float]]:
    """Scene (float64), map, tiny rig and a pose on the lane, 30 % along the garage."""
    scene, world_map = _scene_sh3()
    p = get_preset("tiny")
    g = world_map["garage"]
    return scene, world_map, avm_rig(p.width, p.height, p.bev_px), (g["x"][0] + 0.3 * (g["x"][1] - g["x"][0]),
                                                                      g["lanes"][0], 0.3)


IMAGE_TOL = f32_tol(1.0, ulps=256)
"""Each pixel blends dozens of Gaussians that moved by about one float32 rounding: 256 ulps at 1.0 (3e-5) is
ten times what was measured and 1/130 of an 8-bit level."""


def _same_images(got: dict[str, torch.Tensor], want: dict[str, torch.Tensor]) -> None:
    assert got.keys() == want.keys()
    for name in want:
        assert (got[name] - want[name]).abs().max().item() <= IMAGE_TOL, name


@pytest.mark.parametrize("case", CASES)
def test_foreign_frame_round_trip_keeps_gaussians_and_renders(case: str, garage, tmp_path: Path) -> None:
    """Written in a foreign frame (float32 file), read back with the same flags: the same Gaussians and images."""
    frame, T = CASES[case]
    scene, _, rig, pose = garage
    path = tmp_path / "foreign.ply"
    M = T_parksim_ply(frame, T)
    write_ply(scene, path, M)
    stored = GaussianScene.load_ply(path, dtype=torch.float64)   # the float32 values in the foreign frame
    assert (stored.means - scene.means).abs().max() > 0.5         # it really is another frame
    back = read_ply(path, M, dtype=torch.float64)
    s = 1.0 if T is None else similarity_parts(T)[0]
    # rounding to float32 moved each stored value by <= 1/2 ulp; the similarity scales positions by s, and its
    # orthogonal parts spread a vector's rounding over its components (at most sqrt(2l+1)/2 ulp for an SH band)
    assert (back.means - scene.means).abs().max() <= s * f32_tol(stored.means, ulps=1)
    assert (back.log_scales - scene.log_scales).abs().max() <= f32_tol(stored.log_scales, ulps=1)
    assert (back.opacity_logits - scene.opacity_logits).abs().max() <= f32_tol(stored.opacity_logits, ulps=0.5)
    assert (back.sh - scene.sh).abs().max() <= f32_tol(stored.sh, ulps=1.5)
    sign = torch.sign((back.quats * scene.quats).sum(dim=1, keepdim=True))   # q and -q are the same rotation
    assert (sign * back.quats - scene.quats).abs().max() <= f32_tol(stored.quats, ulps=1)
    want = render(scene.to(torch.float32), rig, pose).images
    _same_images(render(read_ply(path, M), rig, pose).images, want)


# A Gaussian 5 m ahead and 1 m up, flat across the forward axis, brightest when seen looking forward:
# (position, forward, up) written in each convention's own axes, as docs/bundle.md defines them.
CONVENTIONS = {"parksim": ((5, 0, 1), (1, 0, 0), (0, 0, 1)), "opencv": ((0, -1, 5), (0, 0, 1), (0, -1, 0)),
               "colmap": ((0, -1, 5), (0, 0, 1), (0, -1, 0)), "opengl": ((0, 1, -5), (0, 0, -1), (0, 1, 0))}
C1 = math.sqrt(3 / (4 * math.pi))
"""The degree-1 real SH constant."""


def test_every_frame_is_checked_and_offered() -> None:
    assert set(CONVENTIONS) == set(FRAMES)
    for name in FRAMES:
        args = build_parser().parse_args(["bundle", "from-ply", "a.ply", "--rig", "r", "-o", "o", "--frame", name])
        assert args.frame == name


@pytest.mark.parametrize("frame", CONVENTIONS)
def test_frame_names_mean_what_the_docs_say(frame: str, tmp_path: Path) -> None:
    position, forward, up = (torch.tensor(v, dtype=torch.float64) for v in CONVENTIONS[frame])
    R = torch.stack([torch.linalg.cross(up, forward), up, forward], 1)   # local z (the thin axis) = forward
    sh = torch.zeros(1, 4, 3, dtype=torch.float64)
    # the degree-1 basis is C1 * (-y, z, -x), so these coefficients give colour C1 * (d . forward) + 0.5
    sh[0, 1:, :] = torch.stack([-forward[1], forward[2], -forward[0]])[:, None].expand(3, 3)
    ply = GaussianScene(position[None], quaternion_from_rotation(R)[None],
                        torch.tensor([[math.log(0.5), math.log(0.5), math.log(0.01)]], dtype=torch.float64),
                        torch.tensor([2.0], dtype=torch.float64), sh, 1)
    ply.save_ply(tmp_path / "one.ply")
    got = read_ply(tmp_path / "one.ply", T_parksim_ply(frame), dtype=torch.float64)
    assert torch.allclose(got.means[0], torch.tensor([5.0, 0.0, 1.0], dtype=torch.float64), atol=1e-12)
    thin_axis = rotation_from_quaternion(got.quats)[0][:, 2]
    assert torch.allclose(thin_axis.abs(), torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), atol=1e-12)
    x, z = torch.eye(3, dtype=torch.float64)[[0, 2]]
    bright = eval_sh(got.sh, x[None], 1)
    assert torch.allclose(bright, eval_sh(ply.sh, forward[None], 1), atol=1e-12)
    assert torch.allclose(bright, torch.full((1, 3), C1 + 0.5, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(eval_sh(got.sh, z[None], 1), eval_sh(ply.sh, up[None], 1), atol=1e-12)
    assert torch.allclose(eval_sh(got.sh, z[None], 1), torch.full((1, 3), 0.5, dtype=torch.float64), atol=1e-12)


@pytest.mark.parametrize("text", [False, True], ids=["binary", "ascii"])
def test_other_writers_layouts_read_the_same(text: bool, tmp_path: Path) -> None:
    """Exporters differ: double properties, no normals, extra uchar colours (strided float64 columns), ASCII."""
    scene = GaussianScene.random(50, sh_degree=2, seed=1)
    scene.save_ply(tmp_path / "inria.ply")
    v = PlyData.read(str(tmp_path / "inria.ply"))["vertex"].data
    names = [n for n in v.dtype.names if n not in ("nx", "ny", "nz")]
    data = np.empty(len(v), dtype=[(n, "f8") for n in names] + [("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for n in names:
        data[n] = v[n]
    data["red"] = data["green"] = data["blue"] = 200
    PlyData([PlyElement.describe(data, "vertex")], text=text).write(str(tmp_path / "other.ply"))
    want, got = (read_ply(tmp_path / f, T_parksim_ply("opengl")) for f in ("inria.ply", "other.ply"))
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        assert torch.equal(getattr(got, name), getattr(want, name)), name


def test_transform_argument_forms(tmp_path: Path) -> None:
    numbers = [float(v) for v in SIMILARITY.ravel()]
    (tmp_path / "t.json").write_text(json.dumps(SIMILARITY.tolist()))
    (tmp_path / "t.txt").write_text("\n".join(" ".join(repr(v) for v in row) for row in SIMILARITY.tolist()))
    np.save(tmp_path / "t.npy", SIMILARITY)
    for tokens in ([str(tmp_path / "t.json")], [str(tmp_path / "t.txt")], [str(tmp_path / "t.npy")],
                   [repr(v) for v in numbers], [",".join(repr(v) for v in numbers)]):
        assert np.array_equal(read_transform(tokens), SIMILARITY), tokens
    with pytest.raises(ValueError, match="16 numbers, got 15"):
        read_transform([repr(v) for v in numbers[:15]])
    shear = np.eye(4)
    shear[0, 1] = 0.1
    with pytest.raises(ValueError, match="similarity"):
        similarity_parts(shear)
    projective = np.eye(4)
    projective[3, 0] = 0.1
    with pytest.raises(ValueError, match="last row"):
        similarity_parts(projective)


def _cli(capsys, *argv: str) -> tuple[int, str, str]:
    rc = main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


def test_cli_bundle_loads_renders_and_serves(garage, tmp_path: Path, capsys) -> None:
    scene, world_map, rig, pose = garage
    write_ply(scene, tmp_path / "scene.ply", T_parksim_ply("colmap", SIMILARITY))
    (tmp_path / "data").mkdir()
    rig.save(tmp_path / "data" / "rig.json")
    (tmp_path / "data" / "map.json").write_text(json.dumps(world_map))
    (tmp_path / "T.json").write_text(json.dumps(SIMILARITY.tolist()))
    out = tmp_path / "bundle"
    rc, text, err = _cli(capsys, "bundle", "from-ply", str(tmp_path / "scene.ply"), "--rig", str(tmp_path / "data"),
                         "-o", str(out), "--frame", "colmap", "--transform", str(tmp_path / "T.json"),
                         "--map", str(tmp_path / "data"))
    assert (rc, err) == (0, "") and "3000 Gaussians, SH degree 3" in text
    b = bundle_io.load(out)
    assert b.map == world_map and b.rig.to_dict() == rig.to_dict()
    assert b.meta["ply_import"]["frame"] == "colmap" and b.meta["ply_import"]["transform"] == SIMILARITY.tolist()
    _same_images(render(b.scene, b.rig, pose).images, render(scene.to(torch.float32), rig, pose).images)
    frame = LocalSim(out).render(list(pose))
    rc, _, err = _cli(capsys, "render", str(out), "--pose", ",".join(map(str, pose)), "-o", str(tmp_path / "png"))
    assert (rc, err) == (0, "")
    for name, image in frame.images.items():
        assert np.array_equal(to_uint8(read_image(tmp_path / "png" / f"{name}.png")), image), name


def test_cli_undoes_nerfstudio_dataparser_transform(garage, tmp_path: Path, capsys) -> None:
    """A splatfacto export lives in p_ns = s (A p + b) of the world nerfstudio read (here COLMAP axes)."""
    scene, _, rig, pose = garage
    A, b, s = ROTATION, np.array([0.3, -1.0, 2.0]), 0.15
    (tmp_path / "dataparser_transforms.json").write_text(
        json.dumps({"transform": np.concatenate([A, b[:, None]], 1).tolist(), "scale": s}))
    to_colmap = np.eye(4)
    to_colmap[:3, :3] = FRAMES["colmap"].T
    transform_scene(transform_scene(scene, to_colmap), _similarity(s, A, tuple(s * b))).save_ply(tmp_path / "ns.ply")
    rig.save(tmp_path / "rig.json")
    out = tmp_path / "bundle"
    rc, _, err = _cli(capsys, "bundle", "from-ply", str(tmp_path / "ns.ply"), "--rig", str(tmp_path / "rig.json"),
                      "-o", str(out), "--frame", "colmap", "--dataparser-transforms",
                      str(tmp_path / "dataparser_transforms.json"))
    assert (rc, err) == (0, "")
    got = bundle_io.load(out)
    stored = GaussianScene.load_ply(tmp_path / "ns.ply", dtype=torch.float64)
    sorted_means = np.sort(got.scene.means.double().numpy(), axis=0)   # the bundle is in Morton order
    want = np.sort(scene.means.numpy(), axis=0)
    # the stored float32 rounding, scaled back by 1/s, then rounded to float32 again in the bundle
    assert np.abs(sorted_means - want).max() <= f32_tol(stored.means, ulps=1) / s + f32_tol(want, ulps=0.5)
    _same_images(render(got.scene, got.rig, pose).images, render(scene.to(torch.float32), rig, pose).images)


def test_cli_bundle_without_map_serves_and_says_so(garage, tmp_path: Path, capsys) -> None:
    scene, _, rig, pose = garage
    scene.save_ply(tmp_path / "scene.ply")
    rig.save(tmp_path / "rig.json")
    out = tmp_path / "bundle"
    rc, text, err = _cli(capsys, "bundle", "from-ply", str(tmp_path / "scene.ply"), "--rig", str(tmp_path / "rig.json"),
                         "-o", str(out))
    assert (rc, err) == (0, "") and "no map.json" in text
    assert not (out / "map.json").exists()
    sim = LocalSim(out)
    info = sim.info()
    assert info["map"] is None and info["recorded_path"] is None
    assert info["bounds"]["x"][0] < info["bounds"]["x"][1]
    assert set(sim.render(list(pose), bev=True).images) == set(rig.names)
    with pytest.raises(ValueError, match="no slot map"):
        ParkingEnv(bundle=out)
    rc, _, err = _cli(capsys, "compact", str(out), "-o", str(tmp_path / "compact"), "--quiet")
    assert rc == 2 and "no map.json" in err and err.count("\n") == 1


def _rewrite(src: Path, dst: Path, drop: tuple[str, ...] = (), nan: str | None = None, rows: int | None = None
             ) -> Path:
    """``src``'s first ``rows`` vertices (all by default) without the ``drop`` properties, one NaN in ``nan``."""
    v = PlyData.read(str(src))["vertex"].data[:rows]
    keep = [n for n in v.dtype.names if n not in drop]
    data = np.empty(len(v), dtype=[(n, "f4") for n in keep])
    for n in keep:
        data[n] = v[n]
    if nan:
        data[nan][3] = np.nan
    PlyData([PlyElement.describe(data, "vertex")]).write(str(dst))
    return dst


def test_bad_input_is_one_line_exit_2_and_writes_nothing(garage, tmp_path: Path, capsys) -> None:
    scene, _, rig, _ = garage
    good = tmp_path / "good.ply"
    scene.subset(torch.arange(20)).save_ply(good)
    rig.save(tmp_path / "rig.json")
    (tmp_path / "empty.ply").write_bytes(b"")
    cases = {
        "missing": ([str(_rewrite(good, tmp_path / "missing.ply", drop=("scale_1", "rot_3")))],
                    "missing field(s) ['scale_1', 'rot_3']"),
        "nan": ([str(_rewrite(good, tmp_path / "nan.ply", nan="f_rest_7"))], "'f_rest_7' has 1 non-finite value"),
        "degree": ([str(_rewrite(good, tmp_path / "deg.ply", drop=("f_rest_44",)))], "44 f_rest_* fields"),
        "no gaussians": ([str(_rewrite(good, tmp_path / "none.ply", rows=0))], "holds no Gaussians"),
        "not a ply": ([str(tmp_path / "empty.ply")], "not a readable PLY"),
        "shear": ([str(good), "--transform", *"1 0.2 0 0 0 1 0 0 0 0 1 0 0 0 0 1".split()], "similarity"),
        "rig": ([str(good), "--rig", str(tmp_path / "nope.json")], "rig file not found"),
        "dataparser": ([str(good), "--dataparser-transforms", str(tmp_path / "rig.json")],
                       "not a nerfstudio dataparser_transforms.json"),
    }
    for name, (args, message) in cases.items():
        argv = ["bundle", "from-ply", *args, "-o", str(tmp_path / "out")]
        if "--rig" not in args:
            argv += ["--rig", str(tmp_path / "rig.json")]
        rc, out, err = _cli(capsys, *argv)
        assert rc == 2 and out == "" and err.count("\n") == 1 and message in err, (name, err)
        assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(("out", ".out"))) == [], name
