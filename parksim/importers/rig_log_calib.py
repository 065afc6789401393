"""Rig-log calibration -> ``Rig``: OpenCV fisheye YAML, WoodScape JSON, OCamCalib (``calib_results.txt`` or the
surround-view JSON), a SensorsCalibration surround-view folder or a ParkSim rig file, each read by its loader in
``parksim.rig`` / ``parksim.camera`` / ``parksim.calib.avm``.

OpenCV YAML and OCamCalib files hold intrinsics only; their ``T_vehicle_camera`` (camera -> vehicle, OpenCV camera
axes, vehicle x forward, y left, z up) come from an extrinsics file, JSON or YAML::

    cameras:
      front: {T_vehicle_camera: [[r00, r01, r02, tx], [r10, r11, r12, ty], [r20, r21, r22, tz], [0, 0, 0, 1]]}
      rear:  {x: -0.98, y: 0.0, z: 0.92, qw: 0.0, qx: 0.61, qy: -0.61, qz: 0.35}   # translation + quaternion
    bev: {width: 600, height: 600, m_per_px: 0.0166667}                           # optional BEV spec

A calibration folder holds one file per camera named by the camera (``front.yaml``, ``rear.json``, ``left.txt``)
and, when needed, ``extrinsics.json``/``.yaml``/``.yml``; a single file is one camera named by its stem, or a whole
ParkSim rig (``rig.json``/``.yaml``); a folder with ``intrinsic/`` and ``extrinsic/`` subfolders is a whole
SensorsCalibration surround-view calibration (``parksim.calib.avm.read_avm``). Cameras are ordered as the extrinsics
file lists them, then by name.
Rotations within ``parksim.geometry.ROTATION_TOLERANCE`` (a calibration printed with 6 decimals) are projected to
the nearest proper rotation and quaternions normalised; ``Corrections`` counts both for the import report.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from .recording import CALIBRATION_ROTATIONS, Corrections, RecordingError, check_pose

if TYPE_CHECKING:
    from ..rig import BEVSpec, Rig, RigCamera

__all__ = ["FORMATS", "CalibFormat", "EXTRINSICS_NAMES", "QUATERNION_TOLERANCE", "detect_format", "read_extrinsics",
           "load_calibration", "unit_quaternions", "rotations"]

FORMATS = {"opencv-yaml": "OpenCV fisheye YAML (camera_matrix, dist_coeffs, resolution)",
           "woodscape": "WoodScape calibration JSON (radial_poly intrinsic and extrinsic)",
           "ocam-txt": "OCamCalib calib_results.txt",
           "ocam-json": "OCam surround-view JSON (cam_K, cam_dist)",
           "parksim": "ParkSim rig file (rig.json/yaml: every camera's intrinsics and T_vehicle_camera)",
           "avm": "SensorsCalibration surround-view folder (intrinsic/ and extrinsic/ JSON per camera, avm.json: "
                  "BEV camera and ground depths)"}
"""``--calib-format`` values and what each reads."""
CalibFormat = Literal["opencv-yaml", "woodscape", "ocam-txt", "ocam-json", "parksim", "avm"]
"""The keys of ``FORMATS``, as a type."""
OWN_EXTRINSICS = ("woodscape", "parksim")
EXTRINSICS_NAMES = ("extrinsics.json", "extrinsics.yaml", "extrinsics.yml")
CALIB_SUFFIXES = (".yaml", ".yml", ".json", ".txt")
QUATERNION_TOLERANCE = 1e-3
"""Largest deviation of a quaternion's norm from 1 accepted (files round); it is then normalised."""
QUATERNION_KEYS = ("qw", "qx", "qy", "qz")


def unit_quaternions(q: np.ndarray, where: list[str], corrected: Corrections | None = None) -> np.ndarray:
    """``q [N, 4]`` (w, x, y, z) normalised, each counted in ``corrected`` (``Corrections.add_quaternion``); a norm
    more than ``QUATERNION_TOLERANCE`` from 1 is an error naming ``where[i]``."""
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(~(np.abs(norm - 1.0) <= QUATERNION_TOLERANCE))
    if len(bad):
        i = int(bad[0])
        raise RecordingError(f"{where[i]}: quaternion (qw, qx, qy, qz) = {q[i].tolist()} has norm {norm[i]:.6g}, "
                             f"more than {QUATERNION_TOLERANCE:g} from 1")
    if corrected is not None:
        for n, label in zip(norm, where):
            corrected.add_quaternion(float(n), f"{label}: quaternion")
    return q / norm[:, None]


def rotations(q: np.ndarray) -> np.ndarray:
    """Unit quaternions ``[N, 4]`` (w, x, y, z) -> rotation matrices ``[N, 3, 3]`` (float64)."""
    import torch

    from ..geometry import rotation_from_quaternion

    return rotation_from_quaternion(torch.from_numpy(np.asarray(q, np.float64))).numpy()


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _has_cam_k(doc: dict[str, Any]) -> bool:
    """An OCam surround-view JSON: ``cam_K`` at the top or under ``{name: {"param": ...}}``."""
    return "cam_K" in doc or any(isinstance(v, dict) and isinstance(v.get("param"), dict) and "cam_K" in v["param"]
                                 for v in doc.values())


def detect_format(path: Path) -> str:
    """The calibration format of ``path``, from its content (see ``FORMATS``)."""
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise RecordingError(f"{path}: not a text calibration file") from None
    head = text.lstrip()
    if head.startswith("%YAML"):
        return "opencv-yaml"
    if head.startswith("{"):
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as e:
            raise RecordingError(f"{path}: not valid JSON: {e}") from None
        if isinstance(doc, dict) and "intrinsic" in doc and "extrinsic" in doc:
            return "woodscape"
        if isinstance(doc, dict) and "cameras" in doc:
            return "parksim"
        if isinstance(doc, dict) and _has_cam_k(doc):
            return "ocam-json"
    else:
        lines = [line for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]
        if lines and all(_is_number(v) for v in lines[0].split()):
            return "ocam-txt"
        import yaml

        try:
            doc = yaml.safe_load(text)
        except yaml.YAMLError:
            doc = None
        if isinstance(doc, dict) and "cameras" in doc:
            return "parksim"
    raise RecordingError(f"{path}: cannot tell its calibration format ({', '.join(FORMATS)}); give --calib-format")


def _read_doc(path: Path) -> Any:
    """A JSON (``.json``) or YAML file's content; errors name the file."""
    import yaml

    try:
        text = path.read_text()
        return json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    except FileNotFoundError:
        raise RecordingError(f"{path}: file not found") from None
    except (json.JSONDecodeError, yaml.YAMLError, UnicodeDecodeError) as e:
        raise RecordingError(f"{path}: cannot parse: {' '.join(str(e).split())}") from None


def _extrinsic(entry: Any, where: str, corrected: Corrections | None) -> np.ndarray:
    """One camera's ``T_vehicle_camera``: a 4x4 (or 3x4) matrix, or x, y, z and a unit quaternion; corrections
    counted in ``corrected``."""
    if not isinstance(entry, dict):
        raise RecordingError(f"{where}: expected a mapping with T_vehicle_camera, or x, y, z, qw, qx, qy, qz")
    try:
        if "T_vehicle_camera" in entry:
            T = np.array(entry["T_vehicle_camera"], dtype=np.float64)
            if T.shape == (3, 4):
                T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
        else:
            values = np.array([entry[k] for k in ("x", "y", "z", *QUATERNION_KEYS)], dtype=np.float64)
            if not np.isfinite(values).all():
                raise RecordingError(f"{where}: x, y, z, qw, qx, qy, qz must be finite, got {values.tolist()}")
            T = np.eye(4)
            T[:3, :3] = rotations(unit_quaternions(values[None, 3:], [where], corrected))[0]
            T[:3, 3] = values[:3]
    except KeyError as e:
        raise RecordingError(f"{where}: no {e.args[0]!r} (give T_vehicle_camera, or x, y, z, qw, qx, qy, qz)") from None
    except (TypeError, ValueError) as e:
        if isinstance(e, RecordingError):
            raise
        raise RecordingError(f"{where}: T_vehicle_camera must be a 4x4 matrix of numbers ({e})") from None
    return check_pose(T, f"{where}: T_vehicle_camera", corrected, CALIBRATION_ROTATIONS)


def read_extrinsics(path: Path, corrected: Corrections | None = None) -> tuple[dict[str, np.ndarray], BEVSpec | None]:
    """Each camera's ``T_vehicle_camera`` (file order; rotations projected and quaternions normalised, counted in
    ``corrected``) and the optional BEV spec of an extrinsics file."""
    from ..rig import BEVSpec, CalibrationError

    doc = _read_doc(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("cameras"), dict) or not doc["cameras"]:
        raise RecordingError(f"{path}: expected a mapping with a non-empty 'cameras' mapping (and optional 'bev')")
    unknown = sorted(set(doc) - {"cameras", "bev"})
    if unknown:
        raise RecordingError(f"{path}: unknown keys {unknown}; an extrinsics file has 'cameras' and 'bev'")
    T = {str(name): _extrinsic(entry, f"{path} camera {name!r}", corrected) for name, entry in doc["cameras"].items()}
    try:
        bev = None if doc.get("bev") is None else BEVSpec.from_dict(doc["bev"])
    except (CalibrationError, TypeError, AttributeError) as e:
        raise RecordingError(f"{path}: bad bev: {e}") from None
    return T, bev


def _camera(name: str, path: Path, fmt: str, T: np.ndarray | None, fov: dict[str, Any]) -> RigCamera:
    """One camera through its format's loader."""
    import torch

    from ..camera import OCamFisheye
    from ..rig import Rig, RigCamera

    if fmt == "woodscape":
        return Rig.from_woodscape({name: path}, **fov).cameras[name]
    if T is None:
        raise RecordingError(f"{path}: {FORMATS[fmt]} has no extrinsics; give camera {name!r} a T_vehicle_camera in "
                             f"an extrinsics file (--extrinsics, or {EXTRINSICS_NAMES[0]} in the calibration folder)")
    T_t = torch.from_numpy(T)
    if fmt == "opencv-yaml":
        return Rig.from_opencv_yaml({name: path}, {name: T_t}, **fov).cameras[name]
    loader = OCamFisheye.from_calib_results if fmt == "ocam-txt" else OCamFisheye.from_json
    return RigCamera(name, loader(path, **fov), T_t)


def _calibration_files(calib: Path, extrinsics: Path | None) -> tuple[list[Path], Path | None]:
    """The per-camera files of a folder (or the one file) and the extrinsics file to use, if any."""
    if not calib.exists():
        raise RecordingError(f"--calib {calib}: no such file or folder")
    if not calib.is_dir():
        return [calib], extrinsics
    files = sorted(p for p in calib.iterdir() if p.is_file() and p.suffix.lower() in CALIB_SUFFIXES
                   and p.name.lower() not in EXTRINSICS_NAMES)
    if not files:
        raise RecordingError(f"--calib {calib}: no calibration file ({', '.join(CALIB_SUFFIXES)}) in the folder")
    stems = [p.stem for p in files]
    clash = sorted({s for s in stems if stems.count(s) > 1})
    if clash:
        raise RecordingError(f"--calib {calib}: several files name camera {clash[0]!r}; keep one file per camera")
    found = [calib / n for n in EXTRINSICS_NAMES if (calib / n).is_file()]
    return files, extrinsics or (found[0] if found else None)


def _count_rig_corrections(rig: Rig, calib: Path, corrected: Corrections | None, matrix: str) -> None:
    """Count each camera's ``rotation_correction`` (a whole-rig reader's, of the file's ``matrix``) in
    ``corrected``."""
    if corrected is not None:
        for name, cam in rig.cameras.items():
            corrected.add(CALIBRATION_ROTATIONS, cam.rotation_correction, f"{calib} camera {name!r}: {matrix}")


def load_calibration(calib: Path, fmt: str | None = None, extrinsics: Path | None = None,
                     max_fov_deg: float | None = None, corrected: Corrections | None = None
                     ) -> tuple[Rig, dict[str, Any]]:
    """The rig of ``--calib`` (file or folder) and notes for the import report (file, format per camera); rotations
    projected and quaternions normalised are counted in ``corrected``."""
    from ..calib.avm import is_avm_folder, read_avm
    from ..rig import Rig

    fov: dict[str, Any] = {} if max_fov_deg is None else {"max_fov_deg": max_fov_deg}
    if fmt == "avm" or (fmt is None and is_avm_folder(calib)):
        if extrinsics is not None:
            raise RecordingError(f"--calib {calib}: a SensorsCalibration folder holds its own extrinsics; "
                                 "give no extrinsics file")
        rig = read_avm(calib, **fov)
        _count_rig_corrections(rig, calib, corrected, "T_CG")
        return rig, {"calibration": str(calib), "calibration_format": "avm"}
    files, extrinsics = _calibration_files(calib, extrinsics)
    formats = {p: fmt or detect_format(p) for p in files}
    if "parksim" in formats.values():
        if calib.is_dir() or extrinsics is not None:
            raise RecordingError(f"{files[0] if calib.is_dir() else calib}: a ParkSim rig file holds every camera "
                                 "with its extrinsics; pass it alone as --calib FILE, without an extrinsics file")
        rig = Rig.load(calib)
        _count_rig_corrections(rig, calib, corrected, "T_vehicle_camera")
        return rig, {"calibration": str(calib), "calibration_format": "parksim"}
    T, bev = read_extrinsics(extrinsics, corrected) if extrinsics is not None else ({}, None)
    by_name = {p.stem: p for p in files}
    unknown = [n for n in T if n not in by_name]
    if unknown:
        raise RecordingError(f"{extrinsics}: camera {unknown[0]!r} has no calibration file in --calib {calib}")
    doubled = [n for n in T if formats[by_name[n]] in OWN_EXTRINSICS]
    if doubled:
        raise RecordingError(f"{extrinsics}: camera {doubled[0]!r} is calibrated by {by_name[doubled[0]]}, which "
                             "holds its own extrinsics; leave it out of the extrinsics file")
    order = [n for n in T] + sorted(n for n in by_name if n not in T)
    cameras = {n: _camera(n, by_name[n], formats[by_name[n]], T.get(n), fov) for n in order}
    rig = Rig(cameras) if bev is None else Rig(cameras, bev)
    kinds = {n: formats[by_name[n]] for n in order}
    return rig, {"calibration": str(calib), "extrinsics": None if extrinsics is None else str(extrinsics),
                 "calibration_format": next(iter(kinds.values())) if len(set(kinds.values())) == 1 else kinds}
