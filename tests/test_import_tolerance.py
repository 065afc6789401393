"""Rotations as real files hold them (rounded to 6 decimals, cast to float32, quaternions a little off unit norm)
import: each is projected to the nearest proper rotation (``parksim.geometry.nearest_rotation``), the largest
correction is reported and equals the one computed here with numpy's SVD; beyond ``ROTATION_TOLERANCE`` and for a
reflection the one-line error names the value; exact inputs are kept bit for bit and the report says nothing was
corrected.

Inputs are built from the session's ``parksim synth tiny``: its nerfstudio export, a COLMAP text model and a rig log
(``parksim.bench.rig_logs``) written from it, its rig.json, and a random 3DGS PLY for ``bundle from-ply``.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from parksim.bench.rig_logs import write_rig_log
from parksim.cli import main
from parksim.data import DatasetReader
from parksim.data.layout import frame_name
from parksim.gaussians import GaussianScene
from parksim.geometry import ROTATION_TOLERANCE, nearest_rotation, quaternion_from_rotation
from parksim.importers.nerfstudio import OPENGL_FROM_OPENCV
from parksim.importers.recording import REPORT_FILE
from parksim.rig import CalibrationError, Rig

POSE_TOL = 1e-6
"""Imported rotations against the exact ones: a 6-decimal or float32 matrix is within ~1e-6 of the rotation it was
written from (5e-7 per entry rounded; the projection moves it by about as much again, toward that rotation)."""
EXACT = 1e-14
"""A projected rotation is orthonormal to float64 round-off."""


# --- independent references ------------------------------------------------------------------------------------------
def quaternion_to_matrix(q: list[float]) -> np.ndarray:
    """A float64 rotation from a (w, x, y, z) quaternion (numpy, Hamilton)."""
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _svd_correction(R: np.ndarray) -> float:
    """Largest entry of |U V^T - R| (numpy's SVD): what the import must report for ``R``."""
    u, _, vt = np.linalg.svd(np.asarray(R, np.float64))
    return float(np.abs(u @ vt - R).max())


def _orthonormality(R: np.ndarray) -> float:
    R = np.asarray(R, np.float64)
    return max(float(np.abs(R.T @ R - np.eye(3)).max()), abs(float(np.linalg.det(R)) - 1.0))


def _stretched(R: np.ndarray, error: float) -> np.ndarray:
    """``R`` with its first column scaled so that ``|R^T R - I|`` is ``error``: a matrix that is no rotation."""
    return R @ np.diag([math.sqrt(1.0 + error), 1.0, 1.0])


def _cli(capsys, *argv: str | Path) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def _one_line(err: str) -> str:
    lines = [line for line in err.splitlines() if not line.startswith("compiling render kernels")]
    assert len(lines) == 1, err
    return lines[0]


# --- the function -----------------------------------------------------------------------------------------------------
def test_nearest_rotation_keeps_exact_bits_projects_rounded_and_refuses_the_rest() -> None:
    R = quaternion_to_matrix([0.3, -0.5, 0.7, 0.2])
    same, correction = nearest_rotation(R)
    assert correction == 0.0 and same.tobytes() == R.tobytes()
    for rounded in (np.round(R, 6), R.astype(np.float32)):
        got, correction = nearest_rotation(rounded)
        assert correction == _svd_correction(rounded) > 0
        assert _orthonormality(got) < EXACT and np.abs(got - R).max() < POSE_TOL
    bad = _stretched(R, 2e-3)
    with pytest.raises(ValueError, match=rf"^not a proper rotation \(.* = {_orthonormality(bad):.2g} > 0.001\)$"):
        nearest_rotation(bad)
    with pytest.raises(ValueError, match=r"= 2 > 0.001\)$"):
        nearest_rotation(R @ np.diag([1.0, 1.0, -1.0]))   # orthonormal, det -1: a mirror is never "fixed"
    assert ROTATION_TOLERANCE == 1e-3


# --- nerfstudio transforms.json ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def exported(tiny_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """tiny as nerfstudio; variants of its transforms.json are written beside it (same images)."""
    out = tmp_path_factory.mktemp("tolerance") / "ns"
    assert main(["export", "nerfstudio", str(tiny_data), "-o", str(out)]) == 0
    return out


def _variant(exported: Path, name: str, change) -> tuple[Path, list[np.ndarray]]:
    """transforms.json with every transform_matrix replaced by ``change(M)``; the file and the matrices written."""
    meta = json.loads((exported / "transforms.json").read_text())
    written = []
    for frame in meta["frames"]:
        M = change(np.array(frame["transform_matrix"], np.float64))
        frame["transform_matrix"] = [[float(v) for v in row] for row in M]
        written.append(np.array(frame["transform_matrix"], np.float64))
    path = exported / f"{name}.json"
    path.write_text(json.dumps(meta))
    return path, written


def _camera_poses(folder: Path) -> dict[str, np.ndarray]:
    """Every stored per-image pose by its image path in the export (``images/<camera>/<frame>.png``)."""
    reader = DatasetReader(folder)
    return {f"images/{c}/{frame_name(f)}.png": reader.camera_pose(c, f).numpy()
            for f in reader.frames for c in reader.rig.names}


def test_exact_transforms_are_kept_bit_for_bit_and_nothing_is_reported(exported: Path, tmp_path: Path,
                                                                        capsys) -> None:
    rc, _, err = _cli(capsys, "import", "nerfstudio", exported, "-o", tmp_path / "out", "--quiet")
    assert rc == 0 and "corrected" not in err
    assert json.loads((tmp_path / "out" / REPORT_FILE).read_text())["corrected"] == {}
    meta = json.loads((exported / "transforms.json").read_text())
    stored = _camera_poses(tmp_path / "out")
    for frame in meta["frames"]:   # scale 1 (no --rig): each pose is the file's matrix with the axes flipped, exactly
        want = np.array(frame["transform_matrix"], np.float64) @ OPENGL_FROM_OPENCV
        assert stored[frame["file_path"]].tobytes() == want.tobytes(), frame["file_path"]


@pytest.mark.parametrize("kind", ["6 decimals", "float32"])
def test_rounded_transforms_import_projected_and_reported(exported: Path, tmp_path: Path, capsys, kind: str) -> None:
    exact = [np.array(f["transform_matrix"], np.float64)
             for f in json.loads((exported / "transforms.json").read_text())["frames"]]
    rounding = (lambda M: np.round(M, 6)) if kind == "6 decimals" else (lambda M: M.astype(np.float32))
    path, written = _variant(exported, kind.replace(" ", "_"), rounding)
    rc, _, err = _cli(capsys, "import", "nerfstudio", path, "-o", tmp_path / "out", "--quiet")
    assert rc == 0
    report = json.loads((tmp_path / "out" / REPORT_FILE).read_text())
    corrections = [_svd_correction(M[:3, :3]) for M in written]
    worst = int(np.argmax(corrections))
    entry = report["corrected"]["rotations"]
    assert entry["largest"] == corrections[worst] and entry["count"] == len(written)
    assert f"frames[{worst}]" in entry["where"] and entry["where"].endswith("transform_matrix")
    assert set(report["corrected"]) == {"rotations"}
    assert _one_line(err).startswith(f"corrected: {len(written)} rotations (largest {corrections[worst]:.2g} at ")
    meta = json.loads(path.read_text())
    stored = _camera_poses(tmp_path / "out")
    for frame, M, E in zip(meta["frames"], written, exact):
        T = stored[frame["file_path"]] @ OPENGL_FROM_OPENCV
        assert _orthonormality(T[:3, :3]) < EXACT
        assert np.abs(T[:3, :3] - E[:3, :3]).max() < POSE_TOL
        assert np.array_equal(T[:3, 3], M[:3, 3])   # only the rotation is projected


@pytest.mark.parametrize("what", ["off by 2e-3", "reflection"])
def test_a_matrix_that_is_no_rotation_is_one_line_naming_the_value(exported: Path, tmp_path: Path, capsys,
                                                                   what: str) -> None:
    def spoil(M: np.ndarray) -> np.ndarray:
        out = M.copy()
        out[:3, :3] = _stretched(M[:3, :3], 2e-3) if what == "off by 2e-3" else M[:3, :3] @ np.diag([1, 1, -1])
        return out

    path, written = _variant(exported, what.replace(" ", "_"), spoil)
    rc, _, err = _cli(capsys, "import", "nerfstudio", path, "-o", tmp_path / "out", "--quiet")
    line = _one_line(err)
    value = f"{_orthonormality(written[0][:3, :3]):.2g}"
    assert rc == 2 and "frames[0]" in line and "transform_matrix: not a proper rotation" in line
    assert line.endswith(f"= {value} > 0.001)"), line
    assert value == ("2" if what == "reflection" else "0.002")
    assert not (tmp_path / "out").exists()


# --- COLMAP -----------------------------------------------------------------------------------------------------------
def _colmap_text(reader: DatasetReader, out: Path, norm: float) -> dict[str, np.ndarray]:
    """A COLMAP text model of the dataset whose image quaternions have norms alternately ``norm`` and ``2 - norm``
    (``repr``: the file holds exactly these); the quaternions written, by image name."""
    out.mkdir(parents=True)
    cams = []
    for i, name in enumerate(reader.rig.names, start=1):
        m = reader.rig.cameras[name].model
        params = [float(m.fx), float(m.fy), float(m.cx) + 0.5, float(m.cy) + 0.5, *map(float, m.k)]
        cams.append(f"{i} OPENCV_FISHEYE {m.width} {m.height} " + " ".join(map(repr, params)))
    (out / "cameras.txt").write_text("\n".join(cams) + "\n")
    lines, written, image_id = [], {}, 1
    for f in reader.frames:
        for i, c in enumerate(reader.rig.names, start=1):
            T_cw = np.linalg.inv(reader.pose(f).numpy() @ reader.rig.cameras[c].T_vehicle_camera.numpy())
            q = quaternion_from_rotation(torch.from_numpy(T_cw[:3, :3])).numpy()
            q = q * (norm if image_id % 2 else 2.0 - norm)
            name = f"{c}/{frame_name(f)}.png"
            written[name] = q
            lines += [f"{image_id} " + " ".join(map(repr, [*q.tolist(), *T_cw[:3, 3].tolist()])) + f" {i} {name}", ""]
            image_id += 1
    (out / "images.txt").write_text("\n".join(lines) + "\n")
    (out / "points3D.txt").write_text("")
    return written


@pytest.mark.parametrize("norm", [1.0, 1.0 + 1e-4])
def test_colmap_quaternions_off_unit_norm_import_with_the_deviation_reported(tiny_data: Path, tmp_path: Path,
                                                                            capsys, norm: float) -> None:
    reader = DatasetReader(tiny_data)
    written = _colmap_text(reader, tmp_path / "model", norm)
    rc, _, err = _cli(capsys, "import", "colmap", tmp_path / "model", "--images", tiny_data / "images", "-o",
                      tmp_path / "out", "--quiet")
    assert rc == 0
    corrected = json.loads((tmp_path / "out" / REPORT_FILE).read_text())["corrected"]
    deviations = {name: abs(float(np.linalg.norm(q)) - 1.0) for name, q in written.items()}
    if norm == 1.0:   # unit to float64 round-off: nothing to report
        assert max(deviations.values()) < 1e-12 and corrected == {} and "corrected" not in err
    else:
        worst = max(deviations, key=deviations.__getitem__)
        entry = corrected["quaternion_norms"]
        assert entry["largest"] == deviations[worst]
        assert entry["count"] == len(written) and worst in entry["where"]
        assert abs(deviations[worst] - 1e-4) < 1e-12 and set(corrected) == {"quaternion_norms"}
        assert _one_line(err).startswith(f"corrected: {len(written)} quaternion norms (largest 0.0001 at ")
    got = DatasetReader(tmp_path / "out")
    for f in reader.frames:
        for c in reader.rig.names:
            want = reader.pose(f).numpy() @ reader.rig.cameras[c].T_vehicle_camera.numpy()
            assert np.abs(got.camera_pose(c, f).numpy() - want).max() < 1e-9, (f, c)


# --- rig-log calibration ----------------------------------------------------------------------------------------------
def _round_numbers(value, decimals: int = 6):
    """Every float in a JSON value rounded to ``decimals`` (as a calibration toolbox prints them)."""
    if isinstance(value, float):
        return round(value, decimals)
    if isinstance(value, list):
        return [_round_numbers(v, decimals) for v in value]
    if isinstance(value, dict):
        return {k: _round_numbers(v, decimals) for k, v in value.items()}
    return value


@pytest.fixture(scope="module")
def rig_log(tiny_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """tiny as a rig log (OpenCV YAML + extrinsics.json, poses.csv, PNG folders) with a copy of its calibration
    whose extrinsics are printed with 6 decimals."""
    root = tmp_path_factory.mktemp("riglog") / "log"
    write_rig_log(tiny_data, root, video=False)
    shutil.copytree(root / "calib", root / "calib6")
    doc = json.loads((root / "calib" / "extrinsics.json").read_text())
    (root / "calib6" / "extrinsics.json").write_text(json.dumps({**doc, "cameras": _round_numbers(doc["cameras"])}))
    return root


@pytest.mark.parametrize("calib", ["calib", "calib6"])
def test_a_rig_log_calibration_printed_with_6_decimals_imports(tiny_data: Path, rig_log: Path, tmp_path: Path,
                                                              capsys, calib: str) -> None:
    rc, _, err = _cli(capsys, "import", "rig-log", "--calib", rig_log / calib, "--poses", rig_log / "poses.csv",
                      "--images", rig_log / "images", "-o", tmp_path / "out", "--quiet")
    assert rc == 0
    corrected = json.loads((tmp_path / "out" / REPORT_FILE).read_text())["corrected"]
    src, got = DatasetReader(tiny_data).rig, DatasetReader(tmp_path / "out").rig
    cameras = json.loads((rig_log / calib / "extrinsics.json").read_text())["cameras"]
    if calib == "calib":   # exact: matrices kept bit for bit (a quaternion's round trip is float64 rounding)
        assert corrected == {} and "corrected" not in err
        for c in src.names:
            a, b = got.cameras[c].T_vehicle_camera, src.cameras[c].T_vehicle_camera
            assert torch.equal(a, b) if "T_vehicle_camera" in cameras[c] else (a - b).abs().max() < 1e-15, c
        return
    matrices = {c: np.array(e["T_vehicle_camera"])[:3, :3] for c, e in cameras.items() if "T_vehicle_camera" in e}
    norms = {c: abs(float(np.linalg.norm([e[k] for k in ("qw", "qx", "qy", "qz")])) - 1.0)
             for c, e in cameras.items() if "qw" in e}
    assert matrices and norms   # the writer uses both forms
    worst = max(matrices, key=lambda c: _svd_correction(matrices[c]))
    entry = corrected["calibration_rotations"]
    assert entry["largest"] == _svd_correction(matrices[worst]) and entry["count"] == len(matrices)
    assert f"camera {worst!r}: T_vehicle_camera" in entry["where"]
    assert corrected["quaternion_norms"]["largest"] == max(norms.values())
    assert _one_line(err).startswith("corrected: ")
    for c in src.names:
        R, want = got.cameras[c].T_vehicle_camera[:3, :3].numpy(), src.cameras[c].T_vehicle_camera[:3, :3].numpy()
        assert _orthonormality(R) < EXACT and np.abs(R - want).max() < POSE_TOL, c


# --- rig.json ---------------------------------------------------------------------------------------------------------
def test_a_rig_file_written_with_6_decimals_or_float32_loads_with_a_warning(tiny_data: Path, tmp_path: Path) -> None:
    doc = json.loads((tiny_data / "rig.json").read_text())
    exact = Rig.from_dict(doc)
    for kind, change in (("6 decimals", lambda T: np.round(T, 6)), ("float32", lambda T: T.astype(np.float32))):
        written = {c: change(np.array(e["T_vehicle_camera"])) for c, e in doc["cameras"].items()}
        spoilt = {**doc, "cameras": {c: {**e, "T_vehicle_camera": written[c].tolist()}
                                     for c, e in doc["cameras"].items()}}
        (tmp_path / "rig.json").write_text(json.dumps(spoilt))
        corrections = {c: _svd_correction(T[:3, :3]) for c, T in written.items()}
        worst = max(corrections, key=corrections.__getitem__)
        with pytest.warns(UserWarning, match=rf"projected to the nearest proper rotation \(largest correction "
                                             rf"{corrections[worst]:.2g}, camera {worst!r}\)"):
            rig = Rig.load(tmp_path / "rig.json")
        for c, cam in rig.cameras.items():
            R = cam.T_vehicle_camera[:3, :3].numpy()
            assert cam.rotation_correction == corrections[c], (kind, c)
            assert _orthonormality(R) < EXACT, (kind, c)
            assert np.abs(R - exact.cameras[c].T_vehicle_camera[:3, :3].numpy()).max() < POSE_TOL, (kind, c)
    mirrored = {**doc, "cameras": {c: {**e, "T_vehicle_camera": (np.array(e["T_vehicle_camera"])
                                                                 @ np.diag([1.0, 1.0, -1.0, 1.0])).tolist()}
                                   for c, e in doc["cameras"].items()}}
    with pytest.raises(CalibrationError, match=r"not a proper rotation \(.* = 2 > 0.001\)"):
        Rig.from_dict(mirrored)


# --- bundle from-ply --transform --------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["6 decimals", "off by 2e-3"])
def test_bundle_from_ply_takes_a_transform_printed_with_6_decimals(tiny_data: Path, tmp_path: Path, capsys,
                                                                   kind: str) -> None:
    GaussianScene.random(200, sh_degree=1, seed=3).save_ply(tmp_path / "scene.ply")
    R = quaternion_to_matrix([0.9, 0.1, -0.2, 0.3])
    T = np.eye(4)
    T[:3, :3] = 1.7 * (np.round(R, 6) if kind == "6 decimals" else _stretched(R, 2e-3))
    T[:3, 3] = (0.25, -1.5, 0.125)
    numbers = [repr(float(v)) for v in T.ravel()]
    rc, out, err = _cli(capsys, "bundle", "from-ply", tmp_path / "scene.ply", "--rig", tiny_data, "-o",
                        tmp_path / "bundle", "--transform", *numbers)
    A = T[:3, :3] / abs(np.linalg.det(T[:3, :3])) ** (1 / 3)
    if kind == "off by 2e-3":
        line = _one_line(err)
        assert rc == 2 and "similarity" in line and f"= {_orthonormality(A):.2g} > 0.001)" in line, line
        assert not (tmp_path / "bundle").exists()
        return
    assert rc == 0 and err == ""
    correction = _svd_correction(A)
    assert f"--transform: rotation projected to the nearest proper rotation (largest correction {correction:.2g})" \
        in out
    meta = json.loads((tmp_path / "bundle" / "bundle.json").read_text())["ply_import"]
    assert meta["transform_correction"] == correction
    applied = np.array(meta["transform"])
    Q = applied[:3, :3] / abs(np.linalg.det(T[:3, :3])) ** (1 / 3)   # the scale of the given transform, kept
    assert _orthonormality(Q) < EXACT and np.abs(Q - R).max() < POSE_TOL
    assert np.array_equal(applied[:3, 3], T[:3, 3])
