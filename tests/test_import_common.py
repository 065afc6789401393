"""The importers' shared part: the checks and all-or-nothing write of a Recording, and the rig fit."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from parksim.data import DatasetReader
from parksim.geometry import pose_from_xyz_rpy
from parksim.importers import Dropped, Recording, RecordingError, write_recording
from parksim.importers.recording import REPORT_FILE
from parksim.importers.rig_fit import fit_rig
from parksim.synth.rig import avm_rig

W, H, N = 32, 24, 6


def _ego(n: int = N) -> np.ndarray:
    """A curving ego path with some pitch and roll, so the fit is not helped by a flat trajectory."""
    return np.stack([pose_from_xyz_rpy(0.4 * i, 0.1 * i * i, 0.02 * i, 0.01 * i, -0.02 * i, 0.15 * i).numpy()
                     for i in range(n)])


def _recording(rng: np.random.Generator, camera_poses: bool = False) -> Recording:
    rig = avm_rig(W, H, bev_px=50)
    ego = _ego()
    images = {(f, c): (lambda img=rng.integers(0, 256, (H, W, 3), dtype=np.uint8): img)
              for f in range(N) for c in rig.names}
    per_image = [{c: T @ rig.cameras[c].T_vehicle_camera.numpy() for c in rig.names} for T in ego]
    return Recording(rig, list(range(N)), [0.1 * f for f in range(N)], images,
                     poses=None if camera_poses else ego, camera_poses=per_image if camera_poses else None,
                     dropped=[Dropped("no pose within 0.05 s", "front", timestamp=9.0)], notes={"calib": "test"})


def test_write_recording_round_trips_and_reports(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    rec = _recording(rng)
    report = write_recording(rec, tmp_path / "ds", "test", test_every=3, progress=False)
    r = DatasetReader(tmp_path / "ds")
    r.validate(deep=True)
    assert r.split == {"train": [1, 2, 4, 5], "test": [0, 3]}
    assert r.meta["source"] == "import" and r.meta["importer"] == "test" and r.meta["calib"] == "test"
    for f in range(N):
        assert torch.equal(r.pose(f), torch.from_numpy(rec.poses[f]))
        for c in rec.rig.names:
            assert np.array_equal((r.image(c, f).numpy() * 255).round().astype(np.uint8), rec.images[(f, c)]())
    saved = json.loads((tmp_path / "ds" / REPORT_FILE).read_text())
    assert saved == report
    assert report["dropped"] == 1 and report["dropped_by_reason"] == {"no pose within 0.05 s": 1}
    assert report["images_per_camera"] == {c: N for c in rec.rig.names}
    steps = np.linalg.norm(np.diff(rec.poses[:, :3, 3], axis=0), axis=1).sum()
    assert report["path_length_m"] == pytest.approx(steps, abs=1e-6)
    assert report["time_span_s"] == pytest.approx(0.5)


def _bad_rotation(rec: Recording) -> None:
    assert rec.poses is not None
    rec.poses[2, :3, :3] *= 1.001


def _decreasing_time(rec: Recording) -> None:
    rec.timestamps[3] = rec.timestamps[1]


def _wrong_size(rec: Recording) -> None:
    rec.images[(4, "rear")] = lambda: np.zeros((H + 1, W, 3), np.uint8)


def _nan_pose(rec: Recording) -> None:
    assert rec.poses is not None
    rec.poses[1, 0, 3] = math.nan


@pytest.mark.parametrize("spoil, message", [
    (_bad_rotation, "ego pose of frame 2: not a proper rotation"),
    (_decreasing_time, "strictly increasing: frame 3"),
    (_wrong_size, r"--strict: image is 32x25 but the calibration says 32x24 \(camera 'rear', frame 4\)"),
    (_nan_pose, "ego pose of frame 1: expected a finite 4x4"),
])
def test_bad_recordings_write_nothing(tmp_path: Path, spoil, message) -> None:
    rec = _recording(np.random.default_rng(1))
    spoil(rec)
    with pytest.raises(RecordingError, match=message):
        write_recording(rec, tmp_path / "ds", "test", progress=False, strict=True)
    assert list(tmp_path.iterdir()) == []


def test_fit_rig_recovers_rig_and_ego_poses() -> None:
    rec = _recording(np.random.default_rng(2), camera_poses=True)
    assert rec.camera_poses is not None
    rig, ego = rec.rig, _ego()
    fit = fit_rig(rec.camera_poses, rig.names, known=rig)
    assert fit.consistent and fit.scale == pytest.approx(1.0, abs=1e-12)
    assert "known rig baselines" in fit.scale_source
    assert fit.poses is not None
    np.testing.assert_allclose(fit.poses, ego, rtol=0, atol=1e-12)
    # Scaled SfM-like poses: the rig's baselines bring them back to metres.
    half = [{c: np.vstack([np.hstack([T[:3, :3], 0.5 * T[:3, 3:]]), T[3:]]) for c, T in p.items()}
            for p in rec.camera_poses]
    fit = fit_rig(half, rig.names, known=rig)
    assert fit.scale == pytest.approx(2.0, rel=1e-12) and fit.consistent
    assert fit.poses is not None
    np.testing.assert_allclose(fit.poses, ego, rtol=0, atol=1e-12)
    assert fit_rig(half, rig.names, known=rig, scale=3.0).scale_source == "--scale"
    rec.rig = avm_rig(W, H, bev_px=77)   # an importer knows no BEV: the known rig's is kept
    assert fit.apply(rec).rig.bev == rig.bev
    # Without a known rig: same relative rig, a vehicle frame of its own (z up within the cameras' mean up).
    free = fit_rig(rec.camera_poses, rig.names)
    assert free.consistent and free.scale == 1.0 and "as given" in free.scale_source
    for c in rig.names:   # relative poses between cameras are those of the true rig
        a = np.linalg.inv(free.T_vehicle_camera[rig.names[0]]) @ free.T_vehicle_camera[c]
        b = np.linalg.inv(rig.cameras[rig.names[0]].T_vehicle_camera.numpy()) @ rig.cameras[c].T_vehicle_camera.numpy()
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    assert abs(free.T_vehicle_camera["front"][2, 3] - free.T_vehicle_camera["rear"][2, 3]) < 0.5


def test_fit_rig_says_when_poses_do_not_fit_a_rig(tmp_path: Path) -> None:
    rec = _recording(np.random.default_rng(3), camera_poses=True)
    assert rec.camera_poses is not None
    rec.camera_poses[4]["left"] = rec.camera_poses[4]["left"].copy()
    rec.camera_poses[4]["left"][:3, 3] += [0.05, 0.0, 0.0]
    fit = fit_rig(rec.camera_poses, rec.rig.names)
    assert not fit.consistent and fit.poses is None and fit.spread_m > 0.02
    assert "renders at camera poses" in fit.message
    assert fit_rig(rec.camera_poses, rec.rig.names, tol_m=0.1).consistent
    out = fit.apply(rec)
    write_recording(out, tmp_path / "ds", "test", progress=False)
    r = DatasetReader(tmp_path / "ds")
    assert r.has_camera_poses and not r.has_vehicle_poses
    assert json.loads((tmp_path / "ds" / REPORT_FILE).read_text())["poses"] == "per-image only"


def test_frame_number_is_the_last_integer_in_the_stem() -> None:
    from parksim.importers.images import frame_number

    assert frame_number("images/front/frame_00012.png", "x") == 12
    assert frame_number("cam2_000007.jpg", "x") == 7
    with pytest.raises(RecordingError, match=r"transforms.json frame 3: no frame number in the file name 'front.png'"):
        frame_number("images/front.png", "transforms.json frame 3")
