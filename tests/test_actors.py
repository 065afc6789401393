"""Gaussian actors: assets (bake, crop, PLY, folders), placement, and rendering with the scene in one pass.

The scenes are baked boxes (``bake_boxes``: the same sampler the assets come from): a red wall 6 m ahead of a front
fisheye, a grey floor, and a green board as the actor, in front of the wall or behind it.
"""

from __future__ import annotations

import json
import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import torch

from parksim.actor_asset import ASSET_VERSION, ActorAsset, AssetError, load_asset, save_asset
from parksim.actor_sources import BAKE_KINDS, CropBox, asset_from_ply, bake, bake_boxes, crop_asset
from parksim.bench.record import read_record
from parksim.bundle import Bundle
from parksim.bundle import save as save_bundle
from parksim.camera import OpenCVFisheye
from parksim.cli import main
from parksim.commands.asset import _KINDS
from parksim.gaussians import GaussianScene
from parksim.geometry import make_transform
from parksim.ply_3dgs import T_parksim_ply, write_ply
from parksim.render import render, render_batch
from parksim.render.actors import Actor, posed_gaussians
from parksim.rig import BEVSpec, Rig, RigCamera
from parksim.synth.garage import Box
from tolerances import f32_tol

_R_FRONT = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
CAMERA_X, CAMERA_Z = 1.0, 1.5          # the front camera in the vehicle frame, looking along +x
WALL_X, BOARD_HALF = 7.0, 0.05         # the wall's centre plane; half the thickness of wall and board
WALL_GAUSSIANS = 2500                  # the world's first rows: the wall, then the floor
GREEN = RED = 0.65 ** (1 / 2.2)        # a baked side face of a pure colour (lit 0.65, sRGB)
FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh")


def rig() -> Rig:
    """One 128x96 fisheye 1.5 m up looking forward (its axis through pixel (64, 48)), a 64 px BEV at 0.3 m/px
    whose pixel (row 45 - k, column 32) is the ground point (0.3 k, 0)."""
    model = OpenCVFisheye(128, 96, 24.0, 24.0, 64.0, 48.0, [0.0, 0.0, 0.0, 0.0])
    T = make_transform(_R_FRONT, torch.tensor([CAMERA_X, 0.0, CAMERA_Z], dtype=torch.float64))
    return Rig({"front": RigCamera("front", model, T)}, BEVSpec(64, 64, 0.3, center_x=4.05, center_y=0.15))


RIG = rig()


def bev_pixel(x: float) -> tuple[int, int]:
    """The BEV pixel (row, column) of the ground point (x, 0), exact for x a multiple of 0.3 m."""
    u, v, _ = (RIG.bev.K_ipm @ torch.tensor([x, 0.0, 1.0], dtype=torch.float64)).tolist()
    assert abs(u - round(u)) < 1e-9 and abs(v - round(v)) < 1e-9
    return round(v), round(u)


def box(x: float, length: float, width: float, height: float, rgb: tuple[float, float, float], z0: float = 0.0) -> Box:
    return Box(x, 0.0, z0, height, length, width, 0.0, "test", rgb)


@pytest.fixture(scope="module")
def world() -> GaussianScene:
    """A red wall across the view at x = 7 and a grey floor, SH degree 1 (as a scene trained so would be)."""
    wall = bake_boxes([box(WALL_X, 2 * BOARD_HALF, 6.0, 3.0, (1.0, 0.0, 0.0))], "wall", WALL_GAUSSIANS, seed=1).scene
    floor = bake_boxes([box(4.0, 24.0, 24.0, 0.0, (0.2, 0.2, 0.2), z0=-0.05)], "floor", 6000, seed=2).scene
    both = [torch.cat([getattr(wall, f), getattr(floor, f)]) for f in FIELDS]
    both[4] = torch.cat([both[4], torch.zeros(len(both[0]), 3, 3)], dim=1)
    return GaussianScene(*both, sh_degree=1)


@pytest.fixture(scope="module")
def board() -> ActorAsset:
    """A green board 2 m wide and 2 m tall, 10 cm thick, facing x."""
    return bake_boxes([box(0.0, 2 * BOARD_HALF, 2.0, 2.0, (0.0, 1.0, 0.0))], "board", 1500, seed=3)


def joined_by_cat(scene: GaussianScene, actors: list[Actor]) -> GaussianScene:
    """The scene and the posed actors concatenated afresh (what staging must equal)."""
    posed = [scene, *(posed_gaussians(a.asset, a.T_world_actor, scene.sh_degree) for a in actors)]
    return GaussianScene(*(torch.cat([getattr(g, f) for g in posed]) for f in FIELDS), sh_degree=scene.sh_degree)


def assert_same(a, b) -> None:
    for name in a.images:
        assert torch.equal(a.images[name], b.images[name]) and torch.equal(a.alpha[name], b.alpha[name])
        assert torch.equal(a.depth[name], b.depth[name])
    assert (a.bev is None and b.bev is None) or torch.equal(a.bev, b.bev)


def test_no_actors_renders_bit_identically(world):
    with torch.no_grad():
        plain = render(world, RIG, (0.0, 0.0, 0.0), bev=True)
        for none in (None, []):
            assert_same(render(world, RIG, (0.0, 0.0, 0.0), bev=True, actors=none), plain)
        batch = render_batch(world, RIG, [(0.0, 0.0, 0.0), (0.5, 0.2, 0.1)], bev=True)
        for a, b in zip(render_batch(world, RIG, [(0.0, 0.0, 0.0), (0.5, 0.2, 0.1)], bev=True, actors=[]), batch):
            assert_same(a, b)


def _render(scene: GaussianScene, actors: list[Actor], path: str):
    """Render the front view + BEV on one of the paths: the fused CPU kernel, the differentiable path (the scene's
    tensors need a gradient), the device kernels (CPU target), or the front view alone of the wall alone with the
    torch reference rasterizer (slow: it tests every Gaussian at every pixel)."""
    if path == "autograd":
        scene = GaussianScene(*(getattr(scene, f).clone().requires_grad_(True) for f in FIELDS), scene.sh_degree)
        out = render(scene, RIG, (0.0, 0.0, 0.0), bev=True, actors=actors)
        out.images["front"].sum().backward()
        assert scene.means.grad is not None and bool(scene.means.grad.abs().sum() > 0)
        return type(out)(*({k: v.detach() for k, v in d.items()} for d in (out.images, out.alpha, out.depth)),
                         out.bev.detach())
    with torch.no_grad():
        if path == "torch":
            return render(scene.subset(torch.arange(WALL_GAUSSIANS)), RIG, (0.0, 0.0, 0.0), actors=actors,
                          backend="torch")
        return render(scene, RIG, (0.0, 0.0, 0.0), bev=True, actors=actors, projector={"fused": "auto",
                                                                                     "device": "device"}[path])


@pytest.mark.parametrize("path", ["fused", "autograd", "device", "torch"])
def test_actor_occludes_and_is_occluded(world, board, path):
    sigma = {"board": float(board.scene.log_scales[:, 0].exp().max()), "wall": float(world.log_scales[0, 0].exp())}
    axis = (48, 64)                                    # the front camera's optical axis, 1.5 m above the floor
    front = _render(world, [Actor(board, (4.0, 0.0, 0.0))], path)
    behind = _render(world, [Actor(board, (10.0, 0.0, 0.0))], path)
    for out, colour, face_x, what in ((front, 1, 4.0 - BOARD_HALF, "board"), (behind, 0, WALL_X - BOARD_HALF, "wall")):
        rgb = out.images["front"][axis].double()
        # a baked face is opaque up to light through ~20 layers of discs; its colour is that of a lit side face
        assert rgb[colour] == pytest.approx(GREEN if what == "board" else RED, abs=5e-3) and rgb[1 - colour] < 5e-3
        # depth: discs within 3 sigma of the ray are up to (3 sigma)^2 / 2d farther than the face
        distance = face_x - CAMERA_X
        assert float(out.depth["front"][axis]) == pytest.approx(distance, abs=(3 * sigma[what]) ** 2 / (2 * distance))
    if path == "torch":
        return
    # BEV: the ground at x = 12 m is seen through the board when it stands in front, else on the wall (0.7 m up,
    # 2.6 px above its foot); at x = 5.1 m through the board, else the floor (grey, neither red nor green)
    far, near = bev_pixel(12.0), bev_pixel(5.1)
    assert front.bev[far][1] > 0.7 and front.bev[far][0] < 0.02 and front.bev[near][1] > 0.7
    assert behind.bev[far][0] > 0.7 and behind.bev[far][1] < 0.02
    grey = behind.bev[near]
    assert float(grey.max() - grey.min()) < 0.02 and 0.3 < float(grey[0]) < 0.6


def test_actor_footprint_moves_with_its_pose(world, board):
    x, y, yaw = 3.0, -2.0, 0.6
    c, s = math.cos(yaw), math.sin(yaw)
    (x0, y0, _), (x1, y1, _) = board.box
    expected = np.array([[x + c * px - s * py, y + s * px + c * py] for px, py in [(x1, y1), (x0, y1), (x0, y0),
                                                                                    (x1, y0)]])
    actor = Actor(board, (x, y, yaw))
    np.testing.assert_allclose(actor.footprint(), expected, rtol=0, atol=1e-15 * 8)
    obstacle = board.obstacle((x, y, yaw), "board")
    assert obstacle["center"] == pytest.approx([x, y], abs=1e-15) and obstacle["yaw"] == pytest.approx(yaw)
    assert obstacle["size"] == pytest.approx([x1 - x0, y1 - y0]) and obstacle["z"] == list(board.box[0][2:]) + [2.0]
    # in the render: the board moved 3 m sideways no longer stands between the camera and the ground at x = 5.1 m
    with torch.no_grad():
        aside = render(world, RIG, (0.0, 0.0, 0.0), bev=True, actors=[Actor(board, (4.0, 3.0, 0.0))])
    assert aside.bev[bev_pixel(5.1)][1] < 0.6
    with pytest.raises(ValueError, match="rigid"):
        Actor(board, torch.diag(torch.tensor([2.0, 2.0, 2.0, 1.0], dtype=torch.float64)))


def test_staging_equals_a_fresh_concatenation_frame_after_frame(world, board):
    person = bake("pedestrian", count=300, seed=4)
    frames = [[Actor(board, (4.0, 0.0, 0.0)), Actor(person, (5.0, 1.0, 0.3))],
              [Actor(board, (4.0, 0.0, 0.0)), Actor(person, (5.0, 1.2, 0.3))],   # one actor moved
              [Actor(person, (5.0, 1.2, 0.3))],                                     # one gone: rows shift
              [Actor(person, (5.0, 1.2, 0.3)), Actor(board, (9.0, -1.0, 0.5)), Actor(person, (3.0, -1.0, 2.0))]]
    with torch.no_grad():
        for actors in frames:
            assert_same(render(world, RIG, (0.0, 0.0, 0.0), bev=True, actors=actors),
                        render(joined_by_cat(world, actors), RIG, (0.0, 0.0, 0.0), bev=True))
        changed = GaussianScene(*(getattr(world, f).clone() for f in FIELDS), world.sh_degree)
        render(changed, RIG, (0.0, 0.0, 0.0), actors=frames[0])
        changed.sh[:, 0] += 0.5    # in place: the staged copy of the scene must not be reused
        assert_same(render(changed, RIG, (0.0, 0.0, 0.0), actors=frames[0]),
                    render(joined_by_cat(changed, frames[0]), RIG, (0.0, 0.0, 0.0)))
        # threads rendering the same scene at once each get their own staging buffer
        sets = [[Actor(board, (3.0 + 0.5 * k, 0.2 * k, 0.1 * k))] for k in range(8)]
        alone = [render(world, RIG, (0.0, 0.0, 0.0), actors=a) for a in sets]
        with ThreadPoolExecutor(4) as pool:
            together = list(pool.map(lambda a: render(world, RIG, (0.0, 0.0, 0.0), actors=a), sets))
    for a, b in zip(together, alone):
        assert_same(a, b)


def test_crop_round_trip_renders_the_original(world):
    scene = GaussianScene.random(3000, bounds=((2.0, -4.0, 0.0), (12.0, 4.0, 2.0)), sh_degree=3, seed=5,
                                 scale_range=(0.05, 0.3))
    crop = CropBox(6.0, 0.5, 0.7, 3.0, 2.0, 0.0, 1.5)
    asset = crop_asset(scene, crop, "cut")
    inside = crop.contains(scene.means)
    assert len(asset.scene) == int(inside.sum()) > 50 and asset.scene.sh_degree == 3
    back = posed_gaussians(asset, crop.pose)
    ref = scene.subset(inside).to(torch.float64)
    # float64 maths both ways; each way rounds the means to float32 once, at the magnitude of the world's means
    torch.testing.assert_close(back.means.double(), ref.means, rtol=0, atol=float(f32_tol(ref.means, 4)))
    torch.testing.assert_close(back.sh.double(), ref.sh, rtol=0, atol=float(f32_tol(ref.sh, 16)))
    with torch.no_grad():
        original = render(scene, RIG, (0.0, 0.0, 0.0), bev=True)
        placed = render(scene.subset(~inside), RIG, (0.0, 0.0, 0.0), bev=True, actors=[Actor(asset, crop.pose)])
    # the same Gaussians up to a float32 rounding of each parameter, composited in the same depth order
    for name in original.images:
        for got, want in ((placed.images, original.images), (placed.alpha, original.alpha),
                          (placed.depth, original.depth)):
            torch.testing.assert_close(got[name], want[name], rtol=0, atol=float(f32_tol(want[name], 8)))
    torch.testing.assert_close(placed.bev, original.bev, rtol=0, atol=float(f32_tol(original.bev, 8)))
    with pytest.raises(ValueError, match="holds none"):
        crop_asset(scene, CropBox(50.0, 0.0, 0.0, 1.0, 1.0, 0.0, 1.0), "empty")


def test_bake_is_deterministic_and_inside_its_box():
    assert _KINDS == BAKE_KINDS
    for kind in ("car", "van", "pedestrian"):
        a, b = bake(kind, count=400, seed=7), bake(kind, count=400, seed=7)
        assert all(torch.equal(getattr(a.scene, f), getattr(b.scene, f)) for f in FIELDS)
        lo, hi = (torch.tensor(c, dtype=torch.float32) for c in a.box)
        assert bool(((a.scene.means >= lo - 1e-6) & (a.scene.means <= hi + 1e-6)).all())
    assert bake("sedan", count=400, seed=1).box != bake("sedan", count=400, seed=2).box   # proportions by seed
    with pytest.raises(ValueError, match="unknown kind"):
        bake("tram")


def test_asset_folder_round_trip_and_one_line_errors(tmp_path, board):
    folder = save_asset(tmp_path / "board", board)
    loaded = load_asset(folder)
    assert loaded.name == "board" and loaded.box == board.box
    assert all(torch.equal(getattr(loaded.scene, f), getattr(board.scene, f)) for f in FIELDS)
    with pytest.raises(FileExistsError):
        save_asset(folder, board)

    def broken(name: str, edit) -> str:
        bad = tmp_path / name
        save_asset(bad, board)
        edit(bad)
        with pytest.raises(AssetError) as e:
            load_asset(bad)
        assert "\n" not in str(e.value)
        return str(e.value)

    meta = lambda d: json.loads((d / "asset.json").read_text())  # noqa: E731
    write = lambda d, data: (d / "asset.json").write_text(json.dumps(data))  # noqa: E731
    assert "not found" in broken("gone", lambda d: __import__("shutil").rmtree(d))
    assert "asset.json is missing" in broken("nometa", lambda d: (d / "asset.json").unlink())
    assert "gaussians.ply is missing" in broken("noply", lambda d: (d / "gaussians.ply").unlink())
    assert "unreadable JSON" in broken("json", lambda d: (d / "asset.json").write_text("{"))
    assert f"supported version {ASSET_VERSION}" in broken("version", lambda d: write(d, {**meta(d), "version": 9}))
    assert "lo < hi" in broken("box", lambda d: write(d, {**meta(d), "box": [[1, 0, 0], [0, 1, 1]]}))
    assert "'box' must be" in broken("shape", lambda d: write(d, {**meta(d), "box": [1, 2]}))
    assert "name must be" in broken("name", lambda d: write(d, {**meta(d), "name": ""}))
    assert "'meta' must be an object" in broken("meta", lambda d: write(d, {**meta(d), "meta": [1]}))
    assert "not a readable PLY" in broken("ply", lambda d: (d / "gaussians.ply").write_text("junk"))


def test_asset_commands(tmp_path, world, board):
    assert main(["asset", "bake", "pedestrian", "--count", "200", "--seed", "3", "-o", str(tmp_path / "p")]) == 0
    assert load_asset(tmp_path / "p").name == "pedestrian" and len(load_asset(tmp_path / "p").scene) == 200
    # crop a parked board out of a bundle by its map obstacle (10 cm of margin, its foot 1 mm above the floor's
    # discs), and the same by --box
    with_board = joined_by_cat(world, [Actor(board, (4.0, 1.0, 0.4))])
    obstacle = {"center": [4.0, 1.0], "size": [0.3, 2.2], "yaw": 0.4, "z": [0.001, 2.1]}
    save_bundle(tmp_path / "b", Bundle(with_board, RIG, {"obstacles": [obstacle]}, {}))
    assert main(["asset", "crop", str(tmp_path / "b"), "--obstacle", "0", "-o", str(tmp_path / "c")]) == 0
    cut = load_asset(tmp_path / "c")
    colours = 0.28209479177387814 * cut.scene.sh[:, 0] + 0.5
    assert cut.name == "c" and len(cut.scene) > 0.99 * len(board.scene)
    assert bool((colours[:, 1] > 0.7).all() and (colours[:, 0] < 0.05).all())   # board only: no floor, no wall
    assert main(["asset", "crop", str(tmp_path / "b"), "--box", "4,1,0.4,0.3,2.2,0.001,2.1", "-o",
                 str(tmp_path / "d")]) == 0
    assert torch.equal(load_asset(tmp_path / "d").scene.means, cut.scene.means)
    # a 3DGS PLY in OpenCV axes comes back in the asset frame
    write_ply(board.scene, tmp_path / "board.ply", T_parksim_ply("opencv"))
    assert main(["asset", "from-ply", str(tmp_path / "board.ply"), "--frame", "opencv", "-o", str(tmp_path / "e")]) == 0
    ply = load_asset(tmp_path / "e")
    torch.testing.assert_close(ply.scene.means, board.scene.means, rtol=0, atol=float(f32_tol(board.scene.means, 4)))
    assert ply.name == "board" and asset_from_ply(tmp_path / "board.ply", "x", "opencv").name == "x"


@pytest.mark.parametrize("argv, message", [
    (["bake", "car", "--color", "1,2"], "--color takes 3"),
    (["bake", "car", "--color", "1,2,3"], "color must be three numbers in [0, 1]"),
    (["crop", "BUNDLE", "--box", "1,2,3"], "--box takes 7"),
    (["crop", "BUNDLE", "--box", "1,2,0,-1,2,0,1"], "positive length"),
    (["crop", "BUNDLE", "--obstacle", "3"], "has 1 obstacle(s)"),
    (["crop", "NOWHERE", "--obstacle", "0"], "bundle folder not found"),
    (["from-ply", "NOWHERE.ply"], "not found"),
])
def test_asset_command_errors_are_one_line(tmp_path, capsys, world, argv, message):
    save_bundle(tmp_path / "b", Bundle(world, RIG, {"obstacles": [{"center": [7, 0], "size": [1, 6], "yaw": 0,
                                                                    "z": [0, 3]}]}, {}))
    argv = [a.replace("BUNDLE", str(tmp_path / "b")).replace("NOWHERE", str(tmp_path / "nowhere")) for a in argv]
    assert main(["asset", *argv, "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and not (tmp_path / "out").exists()


def test_bench_actors_quick(tiny_data, tmp_path):
    results = tmp_path / "results"
    assert main(["bench", "actors", "--quick", "--quiet", "--dataset", str(tiny_data), "--work", str(tmp_path / "w"),
                 "--results", str(results)]) == 0
    (path,) = results.glob("actors/*.json")
    record = read_record(path)
    figures = {f.target: f for f in record.figures}
    what = "4 cameras 160x120 + BEV 64, 4e3 Gaussians + 10 actors (2,400 Gaussians)"
    assert list(figures) == [f"{what} moving: render", f"{what} moving: overhead over no actors",
                             f"{what} parked: render", f"{what} parked: overhead over no actors",
                             f"{what} moving: staged scene rows vs a fresh torch.cat per frame"]
    for target in (f"{what} moving: render", f"{what} parked: render"):
        f = figures[target]
        assert f.value > 0 and f.cpu is not None and f.cpu > 0 and f.reference is not None and f.reference > 0
        assert f.reference_label == "the same render without actors, same run"
    moving = figures[f"{what} moving: overhead over no actors"]
    assert moving.unit == "%" and moving.goal is None   # the goal holds at the sizes only
    assert moving.value == pytest.approx(100 * (figures[f"{what} moving: render"].value
                                                / figures[f"{what} moving: render"].reference) - 100)
    assert len(record.data["actors"]) == 10 and set(record.data["timings"]) == {"no actors", "moving", "parked",
                                                                                "torch.cat join"}
    assert (path.with_suffix(".png")).is_file()
