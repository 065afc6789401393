"""``parksim import colmap``: COLMAP models written by pycolmap from a synth dataset import back to that dataset.

The models hold the synth rig's OPENCV_FISHEYE intrinsics (principal point + 0.5, COLMAP's pixel convention) and
each image's world -> camera pose; the import must give back the same intrinsics, per-image poses, images and
points, the same dataset from text and binary, and the synth rig and ego poses from the fit.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from parksim.cli import main as cli_main
from parksim.data import DatasetReader
from parksim.data.layout import frame_name
from parksim.importers.colmap import ColmapError, read_model, recording_from_model

pycolmap = pytest.importorskip("pycolmap")

PARKSIM = str(Path(sys.executable).with_name("parksim"))
POINTS = 40
POSE_TOL = 1e-9
"""Poses and intrinsics are float64 through 17-digit text or raw doubles: only rounding of the inverse remains."""


@pytest.fixture(scope="module")
def synth(tiny_data: Path) -> Path:
    """The session's ``parksim synth tiny`` (tests/conftest.py): read only."""
    return tiny_data


def camera_poses(reader: DatasetReader) -> dict[tuple[int, str], np.ndarray]:
    """The synth T_world_camera of every image (float64)."""
    return {(f, c): reader.pose(f).numpy() @ reader.rig.cameras[c].T_vehicle_camera.numpy()
            for f in reader.frames for c in reader.rig.names}


def write_model(reader: DatasetReader, out: Path, scale: float = 1.0, skip: tuple[tuple[int, str], ...] = (),
                camera_model: str = "OPENCV_FISHEYE") -> Path:
    """A pycolmap model of the dataset (translations and points times ``scale``), as text in out/text and
    binary in out/bin; camera ids follow the rig's order, images are named ``<camera>/<frame>.png``, and
    point j is seen by images j + 1 and j + 2."""
    rec = pycolmap.Reconstruction()
    for i, name in enumerate(reader.rig.names, start=1):
        m = reader.rig.cameras[name].model
        extra = list(map(float, m.k)) if camera_model == "OPENCV_FISHEYE" else [0.9]  # else FOV's omega
        params = [float(m.fx), float(m.fy), float(m.cx) + 0.5, float(m.cy) + 0.5, *extra]
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model=camera_model, width=m.width, height=m.height,
                                                        params=params, camera_id=i))
    image_id = 1
    for (f, c), T_wc in camera_poses(reader).items():
        if (f, c) in skip:
            continue
        T_cw = np.linalg.inv(T_wc)
        image = pycolmap.Image(name=f"{c}/{frame_name(f)}.png", camera_id=reader.rig.names.index(c) + 1,
                               image_id=image_id, points2D=pycolmap.Point2DList(
                                   [pycolmap.Point2D(np.array([10.0 + k, 20.0])) for k in range(2)]))
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(T_cw[:3, :3]),
                                                                 scale * T_cw[:3, 3]))
        image_id += 1
    xyz, rgb = reader.points
    for j, (p, colour) in enumerate(zip(xyz[:POINTS].astype(np.float64), rgb[:POINTS])):
        track = pycolmap.Track()  # observations fill the POINTS2D and TRACK records the reader must step over
        track.add_element(j + 1, 0)
        track.add_element(j + 2, 1)
        rec.add_point3D(scale * p, track, colour)
    for sub, write in (("text", rec.write_text), ("bin", rec.write_binary)):
        (out / sub).mkdir(parents=True)
        write(str(out / sub))
    return out


def parksim(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([PARKSIM, *map(str, args)], capture_output=True, text=True)


def import_colmap(model: Path, images: Path, out: Path, *args: str | Path) -> dict:
    """``parksim import colmap`` in this process (the bad inputs below run the console script); its report."""
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert cli_main(["import", "colmap", *map(str, (model, "--images", images, "-o", out, "--quiet", *args))]) == 0
    return json.loads(printed.getvalue())


@pytest.fixture(scope="module")
def models(synth: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_model(DatasetReader(synth), tmp_path_factory.mktemp("models") / "metric")


@pytest.fixture(scope="module")
def imported(synth: Path, models: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The text and binary models imported with the synth rig as --rig."""
    out = tmp_path_factory.mktemp("imported")
    for sub in ("text", "bin"):
        import_colmap(models / sub, synth / "images", out / sub, "--rig", synth)
    return {"text": out / "text", "bin": out / "bin"}


def test_text_model_gives_back_the_intrinsics_poses_images_and_points(synth: Path, imported: dict[str, Path],
                                                                     models: Path) -> None:
    src, got = DatasetReader(synth), DatasetReader(imported["text"])
    got.validate(deep=True)
    assert got.rig.names == src.rig.names and got.frames == src.frames
    for c in src.rig.names:
        a, b = src.rig.cameras[c].model.to_dict(), got.rig.cameras[c].model.to_dict()
        assert a.keys() == b.keys() and a["model"] == b["model"] == "opencv_fisheye"
        for key in ("fx", "fy", "cx", "cy"):
            assert abs(a[key] - b[key]) < POSE_TOL, (c, key)
        assert np.abs(np.subtract(a["k"], b["k"])).max() < POSE_TOL
    expected = camera_poses(src)
    for (f, c), T in expected.items():
        assert np.abs(got.camera_pose(c, f).numpy() - T).max() < POSE_TOL, (f, c)
        assert np.array_equal(got.image(c, f).numpy(), src.image(c, f).numpy()), (f, c)
    xyz, rgb = got.points
    assert np.array_equal(xyz, src.points[0][:POINTS]) and np.array_equal(rgb, src.points[1][:POINTS])
    model = read_model(models / "text")
    assert model.format == "text" and len(model.images) == len(expected) and len(model.xyz) == POINTS


def test_binary_and_text_give_the_same_dataset(imported: dict[str, Path]) -> None:
    def files(root: Path) -> dict[str, bytes]:
        return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
                and p.name not in ("meta.json", "import_report.json")}

    def facts(root: Path, name: str) -> dict:
        skip = {"colmap_model", "colmap_format", "output"}
        return {k: v for k, v in json.loads((root / name).read_text()).items() if k not in skip}

    text, binary = imported["text"], imported["bin"]
    assert files(text) == files(binary) and len(files(text)) > 48
    for name in ("meta.json", "import_report.json"):
        assert facts(text, name) == facts(binary, name)
    assert json.loads((binary / "import_report.json").read_text())["colmap_format"] == "binary"


def test_metric_poses_fit_the_synth_rig_and_ego_poses(synth: Path, imported: dict[str, Path], models: Path,
                                                       tmp_path: Path) -> None:
    src, got = DatasetReader(synth), DatasetReader(imported["text"])
    report = json.loads((imported["text"] / "import_report.json").read_text())
    assert report["rig_consistent"] and report["scale_source"].startswith("known rig baselines")
    assert abs(report["scale"] - 1) < POSE_TOL
    for c in src.rig.names:
        assert np.abs(got.rig.cameras[c].T_vehicle_camera.numpy()
                      - src.rig.cameras[c].T_vehicle_camera.numpy()).max() < POSE_TOL
    assert np.abs(got.poses.numpy() - src.poses.numpy()).max() < POSE_TOL
    # Without --rig the vehicle frame is the cameras' own, but the camera-to-camera geometry is the synth rig's
    # and the ego poses differ from the synth ones by one fixed transform.
    report = import_colmap(models / "bin", synth / "images", tmp_path / "free")
    free = DatasetReader(tmp_path / "free")
    assert report["rig_consistent"] and report["scale"] == 1.0 and report["scale_source"].startswith("as given")
    T = {c: free.rig.cameras[c].T_vehicle_camera.numpy() for c in src.rig.names}
    S = {c: src.rig.cameras[c].T_vehicle_camera.numpy() for c in src.rig.names}
    for c in src.rig.names:
        assert np.abs(np.linalg.inv(T["front"]) @ T[c] - np.linalg.inv(S["front"]) @ S[c]).max() < POSE_TOL
    offsets = [np.linalg.inv(a) @ b for a, b in zip(src.poses.numpy(), free.poses.numpy())]
    assert np.abs(np.array(offsets) - offsets[0]).max() < POSE_TOL


def test_scale_comes_from_the_known_rig_or_from_scale(synth: Path, tmp_path: Path) -> None:
    src = DatasetReader(synth)
    models = write_model(src, tmp_path / "half", scale=0.5)
    report = import_colmap(models / "text", synth / "images", tmp_path / "rig", "--rig", synth / "rig.json")
    # The scale is the median of baseline ratios, each exact up to rounding of float64 differences of ~4 m.
    assert abs(report["scale"] - 2.0) < POSE_TOL and report["scale_source"].startswith("known rig baselines")
    got = DatasetReader(tmp_path / "rig")
    assert np.abs(got.poses.numpy() - src.poses.numpy()).max() < POSE_TOL
    for (f, c), T in camera_poses(src).items():
        assert np.abs(got.camera_pose(c, f).numpy() - T).max() < POSE_TOL
    assert np.abs(got.points[0] - src.points[0][:POINTS]).max() <= 2 * np.spacing(np.abs(src.points[0]).max())

    report = import_colmap(models / "bin", synth / "images", tmp_path / "flag", "--rig", synth, "--scale", "3")
    assert report["scale"] == 3.0 and report["scale_source"] == "--scale"
    got = DatasetReader(tmp_path / "flag")
    for (f, c), T in camera_poses(src).items():
        assert np.abs(got.camera_pose(c, f).numpy()[:3, 3] - 1.5 * T[:3, 3]).max() < POSE_TOL


def test_frames_missing_a_camera_are_dropped_and_counted(synth: Path, tmp_path: Path) -> None:
    src = DatasetReader(synth)
    models = write_model(src, tmp_path / "gaps", skip=((3, "rear"), (7, "left"), (7, "right")))
    rec = recording_from_model(read_model(models / "bin"), synth / "images")
    assert rec.frames == [f for f in src.frames if f not in (3, 7)]
    assert [(d.frame, d.camera) for d in rec.dropped] == [(3, "rear"), (7, "left, right")]
    report = import_colmap(models / "bin", synth / "images", tmp_path / "out")
    assert report["frames"] == len(src.frames) - 2 and report["dropped"] == 2
    assert report["dropped_by_reason"] == {"a camera has no image in this frame": 2}


def test_top_level_images_are_named_after_their_colmap_camera(tmp_path: Path) -> None:
    import cv2

    (tmp_path / "sparse").mkdir()
    (tmp_path / "sparse" / "cameras.txt").write_text("# comment\n7 PINHOLE 8 6 10 11 4.5 3.5\n"
                                                     "2 SIMPLE_PINHOLE 8 6 9 4 3\n")
    (tmp_path / "sparse" / "images.txt").write_text(
        "1 1 0 0 0 0 0 0 7 frame_0012.png\n\n2 1 0 0 0 1 0 0 2 b12.png\n1 2 -1\n"
        "3 1 0 0 0 0 0 0 7 frame_0013.png\n\n")
    (tmp_path / "sparse" / "points3D.txt").write_text("")
    for name in ("frame_0012.png", "b12.png"):
        cv2.imwrite(str(tmp_path / name), np.zeros((6, 8, 3), np.uint8))
    rec = recording_from_model(read_model(tmp_path / "sparse"), tmp_path)
    assert rec.rig.names == ["cam2", "cam7"] and rec.frames == [12]
    assert rec.camera_poses is not None and rec.points is not None
    pin = rec.rig.cameras["cam7"].model.to_dict()
    assert (pin["model"], pin["fx"], pin["fy"], pin["cx"], pin["cy"]) == ("pinhole", 10, 11, 4.0, 3.0)
    simple = rec.rig.cameras["cam2"].model.to_dict()
    assert (simple["fx"], simple["fy"], simple["cx"], simple["cy"]) == (9, 9, 3.5, 2.5)
    assert np.array_equal(rec.camera_poses[0]["cam2"][:3, 3], [-1.0, 0.0, 0.0])  # world -> camera t = (1, 0, 0)
    assert [(d.frame, d.camera) for d in rec.dropped] == [(13, "cam2")] and rec.points[0].shape == (0, 3)


def test_images_default_to_the_folder_beside_the_model_or_its_parent(synth: Path, models: Path,
                                                                      tmp_path: Path) -> None:
    from parksim.importers.colmap import ColmapImporter, ColmapOptions

    colmap = ColmapImporter()
    shutil.copytree(synth / "images", tmp_path / "project" / "images")
    for model in (tmp_path / "project" / "sparse", tmp_path / "project" / "sparse" / "0"):
        shutil.copytree(models / "bin", model, dirs_exist_ok=True)
        rec = colmap.load(ColmapOptions(model))
        assert rec.notes["images_dir"] == str(tmp_path / "project" / "images") and len(rec.frames) == 12
    with pytest.raises(ColmapError, match="no images folder at .*; pass --images"):
        colmap.load(ColmapOptions(models / "bin"))


def test_opencv_images_are_undistorted_to_the_pinhole_with_the_same_k(tmp_path: Path) -> None:
    """A distorted image of a smooth pattern g(x, y) on the normalised image plane, undistorted, must show
    g at the pinhole's pixel rays; a half-pixel slip of the principal point shows as ~4 grey levels."""
    import cv2

    w, h, fx, fy, cx, cy = 96, 72, 80.0, 78.0, 47.5, 35.5  # ParkSim convention (centres at integers)
    dist = np.array([-0.25, 0.06, 0.002, -0.001])

    def g(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return 127.5 + 100.0 * np.sin(6.0 * x + 0.3) * np.cos(5.0 * y - 0.2)

    def distort(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """COLMAP's OPENCV model on normalised coordinates (float64 reference, no cv2)."""
        r2 = x * x + y * y
        radial = 1 + dist[0] * r2 + dist[1] * r2 * r2
        return (x * radial + 2 * dist[2] * x * y + dist[3] * (r2 + 2 * x * x),
                y * radial + dist[2] * (r2 + 2 * y * y) + 2 * dist[3] * x * y)

    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    xd, yd = (u - cx) / fx, (v - cy) / fy
    x, y = xd.copy(), yd.copy()
    for _ in range(200):  # fixed point of x = x + (xd - distort(x)): converges for this mild distortion
        dx, dy = distort(x, y)
        x, y = x + xd - dx, y + yd - dy
    assert max(np.abs(distort(x, y)[0] - xd).max(), np.abs(distort(x, y)[1] - yd).max()) < 1e-12
    distorted = np.clip(np.rint(g(x, y)), 0, 255).astype(np.uint8)
    (tmp_path / "images" / "cam").mkdir(parents=True)
    cv2.imwrite(str(tmp_path / "images" / "cam" / "000004.png"), np.repeat(distorted[..., None], 3, axis=2))
    model = tmp_path / "sparse"
    model.mkdir()
    (model / "cameras.txt").write_text(f"1 OPENCV {w} {h} {fx} {fy} {cx + 0.5} {cy + 0.5} {' '.join(map(str, dist))}\n")
    (model / "images.txt").write_text("1 1 0 0 0 0 0 0 1 cam/000004.png\n\n")
    (model / "points3D.txt").write_text("")
    rec = recording_from_model(read_model(model), tmp_path / "images")
    pin = rec.rig.cameras["cam"].model.to_dict()
    assert (pin["model"], pin["fx"], pin["fy"], pin["cx"], pin["cy"]) == ("pinhole", fx, fy, cx, cy)
    assert "OPENCV -> pinhole" in rec.notes["undistorted"]["cam"]
    out = rec.images[(4, "cam")]()[..., 0].astype(np.float64)
    # Rays of undistorted pixels whose distorted source lies well inside the image (bilinear needs neighbours).
    su, sv = distort((u - cx) / fx, (v - cy) / fy)
    su, sv = su * fx + cx, sv * fy + cy
    inside = (su > 1) & (su < w - 2) & (sv > 1) & (sv < h - 2)
    expected = g((u - cx) / fx, (v - cy) / fy)
    # Rounding of the source (0.5) and of the output (0.5), bilinear error (|g''| / 8 < 0.1 level) and cv2's
    # fixed-point remap weights (1/32 px steps: 1/64 px x |grad g| < 8 levels/px = 0.125): 1.225 levels. The
    # measured worst is 0.97; the distortion centre half a pixel off (cx_colmap kept) gives 1.78.
    assert inside.mean() > 0.8 and np.abs(out - expected)[inside].max() < 1.225


def _one_line_error(done: subprocess.CompletedProcess[str]) -> str:
    lines = [line for line in done.stderr.splitlines() if not line.startswith("compiling render kernels")]
    assert done.returncode == 2 and len(lines) == 1, done.stderr
    assert lines[0].startswith("parksim import: error: "), done.stderr
    return lines[0]


def test_bad_inputs_give_one_line_and_write_nothing(synth: Path, models: Path, tmp_path: Path) -> None:
    truncated = tmp_path / "truncated"
    shutil.copytree(models / "bin", truncated)
    data = (truncated / "images.bin").read_bytes()
    (truncated / "images.bin").write_bytes(data[: len(data) // 2])
    fov = write_model(DatasetReader(synth), tmp_path / "fov", camera_model="FOV")
    holes = tmp_path / "holes"   # a wrong --images folder: none of the model's images is there
    holes.mkdir()
    cases = [(truncated, synth / "images", f"{truncated / 'images.bin'}: truncated at byte {len(data) // 2}"),
             (fov / "bin", synth / "images", "camera 1 uses COLMAP model FOV, which ParkSim does not import"),
             (fov / "text", synth / "images", "line 4: camera 1 uses COLMAP model FOV"),
             (models / "text", holes, f"none of the 48 images named in {models / 'text'} is in {holes} (see "
                                      "--images)")]
    for i, (model, images, message) in enumerate(cases):
        out = tmp_path / f"out{i}"
        line = _one_line_error(parksim("import", "colmap", model, "--images", images, "-o", out, "--quiet"))
        assert message in line and not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(("out", ".out"))]


def test_reader_errors_name_the_file(tmp_path: Path, models: Path) -> None:
    with pytest.raises(ColmapError, match="COLMAP model folder not found"):
        read_model(tmp_path / "none")
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "cameras.txt").write_text("1 PINHOLE 8 6 10 10 4 3\n")
    with pytest.raises(ColmapError, match=r"needs cameras, images and points3D.*found \['cameras.txt'\]"):
        read_model(tmp_path / "m")
    (tmp_path / "m" / "images.txt").write_text("1 2 0 0 0 0 0 0 1 a/1.png\n\n")
    (tmp_path / "m" / "points3D.txt").write_text("")
    with pytest.raises(ColmapError, match=r"images.txt: line 1: image 1 \(a/1.png\) .* quaternion of norm 2"):
        read_model(tmp_path / "m")
    (tmp_path / "m" / "images.txt").write_text("1 1 0 0 0 0 0 0 3 a/1.png\n\n")
    with pytest.raises(ColmapError, match=r"camera ids \[3\] that the cameras file lacks"):
        read_model(tmp_path / "m")
    shutil.copytree(models / "bin", tmp_path / "b")
    with open(tmp_path / "b" / "points3D.bin", "ab") as fh:
        fh.write(b"\0\0\0")
    with pytest.raises(ColmapError, match="points3D.bin: 3 bytes after the last record"):
        read_model(tmp_path / "b")


def test_colmap_import_into_an_existing_dataset_reads_the_model_with_our_reader(synth: Path, models: Path,
                                                                                 tmp_path: Path) -> None:
    data = tmp_path / "data"
    shutil.copytree(synth, data)
    (data / "points3d.ply").unlink()
    done = parksim("colmap", "import", models / "text", data)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    # Model and dataset share the world: the similarity is the identity up to rounding.
    assert report["points"] == POINTS and report["position_rmse_m"] < 1e-9 and abs(report["scale"] - 1) < 1e-9
    xyz = DatasetReader(data).points[0]
    assert np.abs(xyz - DatasetReader(synth).points[0][:POINTS]).max() <= 4 * np.spacing(np.float32(40))
