"""Real recordings lose and damage frames: an image absent, cut short or of another size than its camera's drops
its frame with the reason in import_report.json (one mechanism for every importer), --strict refuses instead,
nothing left is one line; --downscale N stores the images N times smaller with the intrinsics scaled to match."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from parksim.bench.rig_logs import stamp_name, write_rig_log
from parksim.cli import main
from parksim.data import DatasetReader
from parksim.data.layout import frame_name
from parksim.importers import importer, write_recording
from parksim.importers.recording import (
    MISSING_IMAGE,
    REPORT_FILE,
    TRUNCATED,
    UNREADABLE_IMAGE,
    WRONG_SIZE,
    RecordingError,
)

ABSENT = {(1, "left"), (6, "rear"), (10, "right")}
CUT = (3, "front")
SMALL = (8, "left")
KEPT = [0, 2, 4, 5, 7, 9, 11]
TOL = 1e-9
"""Intrinsics through transforms.json (17 digits) and the 0.5 px shift each way: ~1e-14; a wrong pixel-centre rule
is off by 0.25 px."""


@pytest.fixture(scope="module")
def exported(tiny_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``parksim synth tiny`` (4 cameras, 160x120, 12 frames) exported to nerfstudio: read only."""
    out = tmp_path_factory.mktemp("drops") / "ns"
    assert main(["export", "nerfstudio", str(tiny_data), "-o", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def messy(exported: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The export as a real capture comes: three listed images absent, one JPEG cut short, one frame at half size."""
    src = tmp_path_factory.mktemp("messy") / "ns"
    shutil.copytree(exported, src)
    for f, c in ABSENT:
        (src / "images" / c / f"{frame_name(f)}.png").unlink()
    png = src / "images" / CUT[1] / f"{frame_name(CUT[0])}.png"
    jpeg = cv2.imencode(".jpg", cv2.imread(str(png)), [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
    png.unlink()
    png.with_suffix(".jpg").write_bytes(jpeg[:int(len(jpeg) * 0.6)])
    meta = json.loads((src / "transforms.json").read_text())
    for frame in meta["frames"]:
        if frame["file_path"] == f"images/{CUT[1]}/{frame_name(CUT[0])}.png":
            frame["file_path"] = str(Path(frame["file_path"]).with_suffix(".jpg"))
    (src / "transforms.json").write_text(json.dumps(meta))
    small = src / "images" / SMALL[1] / f"{frame_name(SMALL[0])}.png"
    assert cv2.imwrite(str(small), cv2.resize(cv2.imread(str(small)), (80, 60), interpolation=cv2.INTER_AREA))
    return src


def _import(args: list[str], out: Path, capfd: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """``parksim import ARGS -o OUT --quiet``: its exit code and all it wrote to file descriptor 2."""
    capfd.readouterr()
    code = main(["import", *args, "-o", str(out), "--quiet"])
    return code, capfd.readouterr().err


def _nothing_written(parent: Path, out: Path) -> None:
    assert not out.exists() and not list(parent.glob(f".{out.name}*"))


def test_absent_truncated_and_wrong_size_images_drop_their_frames_with_the_reason(messy: Path, tmp_path: Path,
                                                                                  capfd) -> None:
    code, err = _import(["nerfstudio", str(messy)], tmp_path / "ds", capfd)
    assert code == 0, err
    report = json.loads((tmp_path / "ds" / REPORT_FILE).read_text())
    assert report["dropped"] == 5 and report["frames"] == len(KEPT)
    assert report["dropped_by_reason"] == {MISSING_IMAGE: 3, TRUNCATED: 1, WRONG_SIZE: 1}
    items = {(d["frame"], d["camera"]): d for d in report["dropped_items"]}
    assert sorted(items) == sorted([*ABSENT, CUT, SMALL])
    for f, c in ABSENT:
        assert items[(f, c)]["reason"] == MISSING_IMAGE
        assert items[(f, c)]["detail"] == f"{messy / 'images' / c / frame_name(f)}.png: image file not found"
    assert items[CUT]["reason"] == TRUNCATED and f"{frame_name(CUT[0])}.jpg: truncated" in items[CUT]["detail"]
    assert items[SMALL]["detail"].endswith(f"{frame_name(SMALL[0])}.png: image is 80x60 but its camera is 160x120")
    reader = DatasetReader(tmp_path / "ds")
    assert reader.frames == KEPT
    reader.validate(deep=True)
    for f in KEPT:
        for c in reader.rig.names:
            src = cv2.cvtColor(cv2.imread(str(messy / "images" / c / f"{frame_name(f)}.png")), cv2.COLOR_BGR2RGB)
            assert np.array_equal((reader.image(c, f).numpy() * 255).round().astype(np.uint8), src)
    summary = [line for line in err.splitlines() if line.startswith("dropped")]
    assert summary == [f"dropped 5 (kept {len(KEPT)} frames): 3 {MISSING_IMAGE}; 1 {TRUNCATED}; 1 {WRONG_SIZE}"]


def test_strict_refuses_at_the_first_defect_in_one_line_and_writes_nothing(messy: Path, tmp_path: Path,
                                                                           capfd) -> None:
    code, err = _import(["nerfstudio", str(messy), "--strict"], tmp_path / "ds", capfd)
    assert code == 2
    first = messy / "images" / "left" / f"{frame_name(1)}.png"
    assert err.count("\n") == 1, err
    assert f"--strict: {first}: image file not found (camera 'left', frame 1)" in err, err
    _nothing_written(tmp_path, tmp_path / "ds")


def test_strict_imports_a_whole_recording(exported: Path, tmp_path: Path, capfd) -> None:
    code, err = _import(["nerfstudio", str(exported), "--strict"], tmp_path / "ds", capfd)
    assert code == 0, err
    assert json.loads((tmp_path / "ds" / REPORT_FILE).read_text())["dropped"] == 0


def test_every_image_absent_is_one_line(exported: Path, tmp_path: Path, capfd) -> None:
    src = tmp_path / "src"
    shutil.copytree(exported, src)
    shutil.rmtree(src / "images")
    code, err = _import(["nerfstudio", str(src)], tmp_path / "ds", capfd)
    assert code == 2 and err.count("\n") == 1, err
    assert f"no frame is left to import; 12 dropped: 12 {MISSING_IMAGE} (first: {src / 'images'}" in err, err
    _nothing_written(tmp_path, tmp_path / "ds")


def test_downscale_halves_the_images_and_scales_the_intrinsics_by_the_pixel_centre_rule(
        tiny_data: Path, exported: Path, tmp_path: Path, capfd) -> None:
    code, err = _import(["nerfstudio", str(exported), "--downscale", "2", "--rig", str(tiny_data)],
                        tmp_path / "half", capfd)
    assert code == 0, err
    report = json.loads((tmp_path / "half" / REPORT_FILE).read_text())
    assert report["downscale"] == 2 and report["dropped"] == 0
    half, full = DatasetReader(tmp_path / "half"), DatasetReader(tiny_data)
    assert half.meta["downscale"] == 2
    for c in full.rig.names:
        m, s = full.rig.cameras[c].model, half.rig.cameras[c].model
        assert (s.width, s.height) == (m.width // 2, m.height // 2) == (80, 60)
        expected = [float(m.fx) / 2, float(m.fy) / 2, (float(m.cx) + 0.5) / 2 - 0.5, (float(m.cy) + 0.5) / 2 - 0.5]
        got = [float(s.fx), float(s.fy), float(s.cx), float(s.cy)]
        assert np.abs(np.subtract(got, expected)).max() < TOL, (c, got, expected)
        assert np.array_equal(s.k.numpy(), m.k.numpy()) and s.max_fov_deg == m.max_fov_deg
        for f in (0, 7):
            src = (full.image(c, f).numpy() * 255).round().astype(np.int32)
            box = (src[0::2, 0::2] + src[1::2, 0::2] + src[0::2, 1::2] + src[1::2, 1::2] + 2) // 4   # 2x2 mean
            got_img = (half.image(c, f).numpy() * 255).round().astype(np.int32)
            assert got_img.shape == (60, 80, 3) and np.abs(got_img - box).max() <= 1


def test_downscale_must_divide_every_camera_size(exported: Path, tmp_path: Path, capfd) -> None:
    code, err = _import(["nerfstudio", str(exported), "--downscale", "7"], tmp_path / "ds", capfd)
    assert code == 2 and err.count("\n") == 1, err
    assert "--downscale 7: camera 'front' is 160x120, not a multiple of 7" in err, err
    _nothing_written(tmp_path, tmp_path / "ds")


def test_an_in_memory_image_of_another_size_drops_its_frame(exported: Path, tmp_path: Path) -> None:
    """Sources other than files (video frames, an importer's own arrays) are checked as they decode."""
    ns = importer("nerfstudio")
    rec = ns.load(ns.Options(exported))
    rec.images[(4, "rear")] = lambda: np.zeros((121, 160, 3), np.uint8)
    report = write_recording(rec, tmp_path / "ds", "nerfstudio", progress=False)
    assert report["dropped_by_reason"] == {WRONG_SIZE: 1}
    (item,) = report["dropped_items"]
    assert {k: item[k] for k in ("reason", "camera", "frame", "detail")} == {
        "reason": WRONG_SIZE, "camera": "rear", "frame": 4,
        "detail": "image is 160x121 but the calibration says 160x120"}
    assert 4 not in DatasetReader(tmp_path / "ds").frames
    with pytest.raises(RecordingError, match=r"^--strict: image is 160x121 .* \(camera 'rear', frame 4\)$"):
        write_recording(rec, tmp_path / "strict", "nerfstudio", progress=False, strict=True)
    _nothing_written(tmp_path, tmp_path / "strict")


def test_rig_log_drops_an_absent_and_a_wrong_size_image(tiny_data: Path, tmp_path: Path, capfd) -> None:
    """A dangling link (a file lost from a linked capture) and a frame at another size, in per-camera folders."""
    options = write_rig_log(tiny_data, tmp_path / "log", video=False)
    images = tmp_path / "log" / "images"
    times = DatasetReader(tiny_data).timestamps
    lost = images / "rear" / stamp_name(times[2])
    lost.unlink()
    os.symlink(tmp_path / "elsewhere.png", lost)
    small = images / "front" / stamp_name(times[9])
    assert cv2.imwrite(str(small), np.zeros((60, 80, 3), np.uint8))
    args = ["rig-log", "--calib", str(options["calib"]), "--poses", str(options["poses"]), "--images", str(images)]
    code, err = _import(args, tmp_path / "ds", capfd)
    assert code == 0, err
    report = json.loads((tmp_path / "ds" / REPORT_FILE).read_text())
    assert report["dropped_by_reason"] == {MISSING_IMAGE: 1, WRONG_SIZE: 1}
    assert [(d["frame"], d["camera"], d["detail"]) for d in report["dropped_items"]] == [
        (2, "rear", f"{lost}: image file not found"),
        (9, "front", f"{small}: image is 80x60 but its camera is 160x120")]
    assert DatasetReader(tmp_path / "ds").frames == [f for f in range(12) if f not in (2, 9)]
    code, err = _import([*args, "--strict"], tmp_path / "strict", capfd)
    assert code == 2 and f"--strict: {lost}: image file not found (camera 'rear', frame 2)" in err, err
    _nothing_written(tmp_path, tmp_path / "strict")


def _colmap_text_model(data: Path, out: Path) -> Path:
    """The dataset as a COLMAP text model (OPENCV_FISHEYE cameras, images ``<camera>/<frame>.png``, no points),
    written by hand from COLMAP's documented format."""
    import torch

    from parksim.geometry import quaternion_from_rotation

    reader = DatasetReader(data)
    out.mkdir(parents=True)
    cameras, images = [], []
    for i, c in enumerate(reader.rig.names, start=1):
        m = reader.rig.cameras[c].model
        params = [float(m.fx), float(m.fy), float(m.cx) + 0.5, float(m.cy) + 0.5, *map(float, m.k)]
        cameras.append(f"{i} OPENCV_FISHEYE {m.width} {m.height} {' '.join(map(repr, params))}")
        for f in reader.frames:
            T_cw = np.linalg.inv(reader.pose(f).numpy() @ reader.rig.cameras[c].T_vehicle_camera.numpy())
            q = quaternion_from_rotation(torch.from_numpy(T_cw[:3, :3])).tolist()
            images += [f"{len(images) // 2 + 1} {' '.join(map(repr, [*q, *T_cw[:3, 3].tolist()]))} {i} "
                       f"{c}/{frame_name(f)}.png", ""]
    (out / "cameras.txt").write_text("\n".join(cameras) + "\n")
    (out / "images.txt").write_text("\n".join(images) + "\n")
    (out / "points3D.txt").write_text("")
    return out


def test_colmap_drops_an_absent_image(tiny_data: Path, tmp_path: Path, capfd) -> None:
    model = _colmap_text_model(tiny_data, tmp_path / "sparse")
    images = tmp_path / "images"
    shutil.copytree(tiny_data / "images", images)
    (images / "left" / f"{frame_name(5)}.png").unlink()
    code, err = _import(["colmap", str(model), "--images", str(images)], tmp_path / "ds", capfd)
    assert code == 0, err
    report = json.loads((tmp_path / "ds" / REPORT_FILE).read_text())
    assert report["dropped_by_reason"] == {MISSING_IMAGE: 1}
    assert [(d["frame"], d["camera"]) for d in report["dropped_items"]] == [(5, "left")]
    assert DatasetReader(tmp_path / "ds").frames == [f for f in range(12) if f != 5]


def test_instant_ngp_drops_an_absent_image_whose_size_it_cannot_read(exported: Path, tmp_path: Path,
                                                                     capfd) -> None:
    """No w, h in the file: instant-ngp takes each image's own size, so an absent image has no lens; its frame is
    dropped once (not again for the cameras it lacks), and --strict refuses it."""
    src = tmp_path / "ngp"
    shutil.copytree(exported, src)
    meta = json.loads((src / "transforms.json").read_text())
    lens = ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "k3", "k4", "transform_matrix")
    frames = [{"file_path": str(Path(fr["file_path"]).with_suffix("")), **{k: {**meta, **fr}[k] for k in lens}}
              for fr in meta["frames"]]
    (src / "transforms.json").write_text(json.dumps({"is_fisheye": True, "frames": frames}))
    (src / "images" / "right" / f"{frame_name(7)}.png").unlink()
    code, err = _import(["instant-ngp", str(src)], tmp_path / "ds", capfd)
    assert code == 0, err
    report = json.loads((tmp_path / "ds" / REPORT_FILE).read_text())
    assert report["dropped_by_reason"] == {MISSING_IMAGE: 1}
    (item,) = report["dropped_items"]
    assert item["frame"] == 7 and item["detail"].endswith(f"images/right/{frame_name(7)}: image file not found")
    assert 7 not in DatasetReader(tmp_path / "ds").frames
    code, err = _import(["instant-ngp", str(src), "--strict"], tmp_path / "strict", capfd)
    assert code == 2 and err.count("\n") == 1 and "--strict: " in err and "image file not found" in err, err
    _nothing_written(tmp_path, tmp_path / "strict")


def test_an_unreadable_file_is_dropped_before_anything_is_decoded(exported: Path, tmp_path: Path) -> None:
    src = tmp_path / "src"
    shutil.copytree(exported, src)
    bad = src / "images" / "front" / f"{frame_name(0)}.png"
    bad.write_bytes(b"not an image at all")
    code = main(["import", "nerfstudio", str(src), "-o", str(tmp_path / "ds"), "--quiet"])
    assert code == 0
    report = json.loads((tmp_path / "ds" / REPORT_FILE).read_text())
    assert report["dropped_by_reason"] == {UNREADABLE_IMAGE: 1}
    assert report["dropped_items"][0]["detail"].startswith(f"{bad}: not a readable image")
