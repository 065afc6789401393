"""Image files cut short (a copy stopped early, a full disk): every importer drops their frames with the reason in
import_report.json, never trains on the grey rows a decoder fills in, and lets no decoder noise through."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from parksim.bench.rig_logs import image_folders, stamp_name, write_rig_log
from parksim.cli import main
from parksim.data import DatasetReader
from parksim.importers.images import TRUNCATED, image_defect
from parksim.importers.recording import REPORT_FILE, UNREADABLE_IMAGE

CUT = {(3, "front"): 0.6, (8, "left"): 0.97}
"""(frame, camera) -> the share of its file's bytes kept: 60 % loses half the rows, 97 % only the last few."""


@pytest.fixture(scope="module")
def exported(tiny_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``parksim synth tiny`` exported to nerfstudio, its images re-encoded as JPEG (transforms.json updated)."""
    out = tmp_path_factory.mktemp("corrupt") / "ns"
    assert main(["export", "nerfstudio", str(tiny_data), "-o", str(out)]) == 0
    meta = json.loads((out / "transforms.json").read_text())
    for frame in meta["frames"]:
        png = out / frame["file_path"]
        assert cv2.imwrite(str(png.with_suffix(".jpg")), _bgr(png), [cv2.IMWRITE_JPEG_QUALITY, 95])
        png.unlink()
        frame["file_path"] = str(Path(frame["file_path"]).with_suffix(".jpg"))
    (out / "transforms.json").write_text(json.dumps(meta))
    return out


@pytest.fixture(scope="module")
def log(tiny_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``parksim synth tiny`` as a rig log: OpenCV YAML calibration and poses.csv (images written per test)."""
    root = tmp_path_factory.mktemp("corrupt-log") / "log"
    write_rig_log(tiny_data, root, video=False)
    return root


def _bgr(path: Path) -> np.ndarray:
    img = cv2.imread(str(path))
    assert img is not None, path
    return img


def _cut(path: Path, share: float) -> None:
    data = path.read_bytes()
    path.write_bytes(data[:int(len(data) * share)])


def _import(args: list[str], out: Path, capfd: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """Run ``parksim import`` on the command line; its exit code and everything written on file descriptor 2
    (where libjpeg and libpng print, past Python's sys.stderr)."""
    capfd.readouterr()
    code = main(["import", *args, "-o", str(out), "--quiet"])
    return code, capfd.readouterr().err


def _check_dropped(out: Path, err: str, dropped: dict[tuple[int, str], float]) -> None:
    report = json.loads((out / REPORT_FILE).read_text())
    assert report["dropped_by_reason"] == {TRUNCATED: len(dropped)}, report
    assert sorted((d["frame"], d["camera"]) for d in report["dropped_items"]) == sorted(dropped)
    assert DatasetReader(out).frames == [f for f in range(12) if f not in {f for f, _ in dropped}]
    assert report["frames"] == 12 - len(dropped)
    assert "Premature end" not in err and "libpng" not in err, err


def test_truncated_jpeg_and_png_are_told_from_whole_ones_by_their_last_bytes(tmp_path: Path) -> None:
    img = np.random.default_rng(0).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    for ext in ("jpg", "png"):
        whole = tmp_path / f"whole.{ext}"
        assert cv2.imwrite(str(whole), img)
        assert image_defect(whole) is None
        padded = tmp_path / f"padded.{ext}"
        padded.write_bytes(whole.read_bytes() + b"\0" * 5000)   # some camera writers pad with zeros
        assert image_defect(padded) is None
        for share in (0.6, 0.97, 0.999):
            cut = tmp_path / f"cut{share}.{ext}"
            cut.write_bytes(whole.read_bytes()[:int(whole.stat().st_size * share)])
            assert image_defect(cut) == TRUNCATED, (ext, share)


def test_nerfstudio_drops_frames_with_a_truncated_jpeg(exported: Path, tmp_path: Path, capfd) -> None:
    src = tmp_path / "src"
    shutil.copytree(exported, src)
    for (f, c), share in CUT.items():
        _cut(src / "images" / c / f"{f:06d}.jpg", share)
    code, err = _import(["nerfstudio", str(src)], tmp_path / "ds", capfd)
    assert code == 0, err
    _check_dropped(tmp_path / "ds", err, CUT)


@pytest.mark.parametrize("ext", ["jpg", "png"])
def test_rig_log_image_folders_drop_frames_with_a_truncated_image(tiny_data: Path, log: Path, tmp_path: Path,
                                                                  capfd, ext: str) -> None:
    images = tmp_path / "images"
    image_folders(tiny_data, images)
    if ext == "jpg":
        for png in images.glob("*/*.png"):
            assert cv2.imwrite(str(png.with_suffix(".jpg")), _bgr(png))
            png.unlink()
    times = DatasetReader(tiny_data).timestamps
    for (f, c), share in CUT.items():
        _cut(images / c / Path(stamp_name(times[f])).with_suffix(f".{ext}"), share)
    code, err = _import(["rig-log", "--calib", str(log / "calib"), "--poses", str(log / "poses.csv"),
                         "--images", str(images)], tmp_path / "ds", capfd)
    assert code == 0, err
    _check_dropped(tmp_path / "ds", err, CUT)


def test_a_camera_with_every_image_truncated_is_one_line_exit_2(exported: Path, tmp_path: Path, capfd) -> None:
    src = tmp_path / "src"
    shutil.copytree(exported, src)
    for jpg in (src / "images" / "rear").iterdir():
        _cut(jpg, 0.6)
    code, err = _import(["nerfstudio", str(src)], tmp_path / "out", capfd)
    assert code == 2
    assert err.count("\n") == 1 and "no frame is left to import; 12 dropped: 12 truncated image file" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]


def test_an_image_that_does_not_decode_is_dropped_or_with_strict_one_line_naming_it(exported: Path, tmp_path: Path,
                                                                                     capfd) -> None:
    """A whole file with broken data (a PNG whose pixel chunk fails its CRC): its frame is dropped with the
    decoder's own message in the report, or with --strict that message joins the one line of the error instead of
    printing a line of its own before it."""
    src = tmp_path / "src"
    shutil.copytree(exported, src)
    bad = src / "images" / "rear" / "000005.jpg"
    png = cv2.imencode(".png", _bgr(bad))[1].tobytes()
    at = png.index(b"IDAT") + 20
    bad.write_bytes(png[:at] + bytes([png[at] ^ 0xFF]) + png[at + 1:])
    assert image_defect(bad) is None
    code, err = _import(["nerfstudio", str(src)], tmp_path / "ds", capfd)
    assert code == 0 and "libpng" not in err, err
    report = json.loads((tmp_path / "ds" / REPORT_FILE).read_text())
    assert report["dropped_by_reason"] == {UNREADABLE_IMAGE: 1}
    (item,) = report["dropped_items"]
    assert (item["camera"], item["frame"]) == ("rear", 5) and 5 not in DatasetReader(tmp_path / "ds").frames
    assert f"{bad}: cannot decode the image" in item["detail"] and "libpng error" in item["detail"], item
    code, err = _import(["nerfstudio", str(src), "--strict"], tmp_path / "out", capfd)
    assert code == 2
    assert err.count("\n") == 1 and f"{bad}: cannot decode the image" in err and "libpng error" in err, err
    assert not (tmp_path / "out").exists()
