"""A SensorsCalibration surround-view (AVM) calibration -> ``Rig`` in ParkSim's vehicle frame.

The format is that of PJLab-ADG SensorsCalibration's ``surround-camera`` tools (``manual_calib/ocam_samples``):
a folder with ``intrinsic/NAME.json`` (OCam intrinsics, read by ``OCamFisheye.from_json``) and
``extrinsic/NAME.json`` (``{"bev-to-NAME-extrinsic": {"param": {"sensor_calib": {"data": 4x4}}}}``, the matrix
``T_CG``) per camera. What the tool keeps in its code, not in files -- the BEV camera ``K_G`` and each camera's
ground depth -- is given by ``avm.json`` (or ``avm.yaml``) in the same folder::

    {"bev_camera": {"width": 1000, "height": 1000, "dX": 0.004, "dY": 0.004},   # K_G; optional cx, cy
     "ground_depth": {"Front": 6.07826, "Left": 6.25217, "Back": 6.31014, "Right": 6.28116},   # or one number
     "bev_center": [1.4, 0.0],                    # optional: ground point under the BEV camera, our frame (m)
     "ego_box": [-1.0, 3.8, -1.0, 1.0]}           # optional: the car in the BEV, masked (our frame, m)

The tool's projection, BEV pixel ``(j, i)`` (column, row) of camera ``C`` to its image:

1. ``P_G = h_C K_G^-1 (j, i, 1)`` with ``K_G = [[1/dX, 0, cx], [0, 1/dY, cy], [0, 0, 1]]`` (``cx = width // 2``,
   ``cy = height // 2`` as the tool's integer division gives): the ground point seen by a virtual pinhole camera
   G looking straight down, the ground plane at depth ``h_C`` (the ground depth) in front of it;
2. ``P_C = T_CG P_G``, then ``(X, Y) = (x_C / z_C, y_C / z_C)``;
3. OCam ``world2cam`` of ``(X, Y, -1)`` with the intrinsics' ``cam_K`` and ``cam_dist`` (column, row).

Frames. C is an OpenCV camera (x right, y down, z forward): the tool's pinhole mode projects
``(fx X + cx, fy Y + cy)`` from the same ``P_C``, so C is ParkSim's camera frame unchanged. G is the BEV camera:
x_G along BEV columns, y_G along BEV rows, z_G down into the ground, origin above the BEV pixel ``(cx, cy)``.
The tool stitches the front camera into the top rows and the left camera into the left columns, so BEV up is
vehicle forward and BEV left is vehicle left: x_G = -y_V (right), y_G = -x_V (backward), z_G = -z_V (down), i.e.
``R_VG = [[0, -1, 0], [-1, 0, 0], [0, 0, -1]]`` (det +1; its own inverse).

Conversion, per camera:

1. ``R_CG`` goes through ``parksim.geometry.nearest_rotation`` (a printed matrix is 6-decimal rounded); the
   largest correction is the camera's ``rotation_correction``.
2. The ground depth. Steps 1-2 see only the direction of ``h_C R_CG n + t_CG``, so a camera's BEV is unchanged
   when its ``t_CG`` and ``h_C`` are scaled together: the format fixes each camera's position only up to its
   own scale, and different ground depths (the tool tunes them per camera) put the cameras' grounds at
   different depths of one G. ParkSim has one ground plane, so each camera's ``t_CG`` is scaled by ``H / h_C``,
   ``H`` the mean ground depth: every camera then sees the ground at depth ``H`` and projects exactly as the
   tool does. With equal depths this is the identity. Translations and depths are taken to be in metres.
3. Our vehicle frame from G: the G origin is ``H`` above the ground point ``bev_center = (x0, y0)``, so
   ``T_VG = [[R_VG, (x0, y0, H)], [0, 0, 0, 1]]`` and ``T_vehicle_camera = T_VG T_CG^-1``. The format knows
   nothing of the rear axle: ``bev_center`` says where the BEV camera stands from it (default the origin).
4. The BEV: ``width x height`` pixels of ``m_per_px = dX H`` (square pixels only: ``dX = dY``), centred so that
   ``BEVSpec.pixel_to_ground`` maps every BEV pixel to the ground point the tool maps it to.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import torch

from ..camera import OCamFisheye
from ..geometry import invert_transform, make_transform, nearest_rotation
from ..rig import BEVSpec, CalibrationError, Rig, RigCamera

__all__ = ["AVM_SPEC_NAMES", "R_VEHICLE_BEV", "is_avm_folder", "read_avm"]

AVM_SPEC_NAMES = ("avm.json", "avm.yaml", "avm.yml")
"""The file holding the BEV camera and ground depths, tried in this order."""
R_VEHICLE_BEV = torch.tensor([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
"""``R_VG``: the tool's BEV-camera axes (x columns, y rows, z down) in our vehicle frame (x forward, y left, z up)."""
_SPEC_KEYS = {"bev_camera", "ground_depth", "bev_center", "ego_box"}
_BEV_KEYS = {"width", "height", "dX", "dY", "cx", "cy"}


def is_avm_folder(path: Path) -> bool:
    """Whether ``path`` is a folder laid out as a SensorsCalibration calibration (``extrinsic/``, ``intrinsic/``).

    Args:
        path: a file or folder.

    Returns:
        True for a folder with both subfolders.
    """
    return path.is_dir() and (path / "extrinsic").is_dir() and (path / "intrinsic").is_dir()


def _read_spec(folder: Path) -> tuple[Path, dict[str, Any]]:
    """The ``avm.json``/``.yaml`` file of ``folder`` and its mapping."""
    import yaml

    found = [folder / n for n in AVM_SPEC_NAMES if (folder / n).is_file()]
    if not found:
        raise CalibrationError(f"{folder}: no {AVM_SPEC_NAMES[0]} (the BEV camera and the ground depths, which the "
                               "SensorsCalibration tools keep in their code)")
    path = found[0]
    try:
        text = path.read_text()
        doc = json.loads(text) if path.suffix == ".json" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError, UnicodeDecodeError) as e:
        raise CalibrationError(f"{path}: cannot parse: {' '.join(str(e).split())}") from None
    if not isinstance(doc, dict) or "bev_camera" not in doc or "ground_depth" not in doc:
        raise CalibrationError(f"{path}: expected a mapping with 'bev_camera' and 'ground_depth'")
    unknown = sorted(set(doc) - _SPEC_KEYS)
    if unknown:
        raise CalibrationError(f"{path}: unknown keys {unknown}; expected {sorted(_SPEC_KEYS)}")
    return path, doc


def _number(value: Any, where: str, positive: bool = False) -> float:
    """``value`` as a finite float (positive if asked); else a one-line error naming ``where``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or (positive and not value > 0):
        raise CalibrationError(f"{where} must be a finite{' positive' if positive else ''} number, got {value!r}")
    return float(value)


def _bev_camera(bev: Any, where: str) -> tuple[int, int, float, float, float]:
    """``(width, height, d, cx, cy)`` of the ``bev_camera`` mapping: ``K_G = [[1/d, 0, cx], [0, 1/d, cy]]``."""
    if not isinstance(bev, dict) or not {"width", "height", "dX", "dY"} <= set(bev) or set(bev) - _BEV_KEYS:
        raise CalibrationError(f"{where}: bev_camera must hold width, height, dX, dY (optional cx, cy), got {bev!r}")
    width, height = bev["width"], bev["height"]
    if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in (width, height)):
        raise CalibrationError(f"{where}: bev_camera width and height must be positive integers, got "
                               f"{width!r}, {height!r}")
    dx, dy = (_number(bev[k], f"{where}: bev_camera {k}", positive=True) for k in ("dX", "dY"))
    if abs(dx - dy) > 1e-9 * dx:
        raise CalibrationError(f"{where}: bev_camera dX = {dx} and dY = {dy} differ; ParkSim's BEV has square pixels")
    cx = _number(bev.get("cx", width // 2), f"{where}: bev_camera cx")
    cy = _number(bev.get("cy", height // 2), f"{where}: bev_camera cy")
    return width, height, dx, cx, cy


def _pair(value: Any, n: int, where: str) -> list[float]:
    """``n`` finite numbers from a list; else a one-line error naming ``where``."""
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise CalibrationError(f"{where} must be a list of {n} numbers, got {value!r}")
    return [_number(v, where) for v in value]


def _depths(value: Any, names: list[str], where: str) -> dict[str, float]:
    """Each camera's ground depth from one number or a ``{camera: depth}`` mapping naming exactly ``names``."""
    if not isinstance(value, dict):
        depth = _number(value, f"{where}: ground_depth", positive=True)
        return dict.fromkeys(names, depth)
    if set(value) != set(names):
        raise CalibrationError(f"{where}: ground_depth names cameras {sorted(value)}; extrinsic/ has {sorted(names)}")
    return {str(n): _number(d, f"{where}: ground_depth of {n!r}", positive=True) for n, d in value.items()}


def _read_T_CG(path: Path) -> torch.Tensor:
    """The 4x4 ``T_CG`` of one extrinsic file (its single entry's ``param.sensor_calib.data``), float64."""
    try:
        doc = json.loads(path.read_text())
        if not isinstance(doc, dict) or len(doc) != 1:
            raise ValueError("expected one entry {\"bev-to-NAME-extrinsic\": {...}}")
        data = next(iter(doc.values()))["param"]["sensor_calib"]["data"]
        T = torch.tensor(data, dtype=torch.float64).reshape(4, 4)
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError, RuntimeError) as e:
        raise CalibrationError(f"{path}: not a SensorsCalibration extrinsic ({type(e).__name__}: "
                               f"{' '.join(str(e).split())})") from None
    if not torch.isfinite(T).all() or T[3].tolist() != [0.0, 0.0, 0.0, 1.0]:
        raise CalibrationError(f"{path}: T_CG must be a finite 4x4 with bottom row 0 0 0 1, got {T.tolist()}")
    return T


def read_avm(folder: str | Path, max_fov_deg: float = 360.0) -> Rig:
    """Read a SensorsCalibration surround-view calibration folder into a ``Rig`` in our vehicle frame.

    Cameras are named by their extrinsic files' stems (``Front``, ``Left``...), ordered as ``ground_depth``
    lists them when it is a mapping, else by name. Each camera's ``rotation_correction`` is the largest change
    ``nearest_rotation`` made to its ``T_CG`` rotation. See the module docstring for the conversion.

    Args:
        folder: the folder with ``intrinsic/``, ``extrinsic/`` and ``avm.json`` (or ``avm.yaml``).
        max_fov_deg: each lens' full field of view (the files do not state it; 360: up to the image corners).

    Returns:
        The rig: ``OCamFisheye`` cameras, ``T_vehicle_camera`` in our vehicle frame, and the tool's BEV as its
        ``BEVSpec``.

    Raises:
        CalibrationError: a missing or malformed file, a camera without intrinsics, a rotation beyond
            ``parksim.geometry.ROTATION_TOLERANCE`` or a BEV camera ParkSim cannot hold; one line naming the file.
    """
    folder = Path(folder)
    if not is_avm_folder(folder):
        raise CalibrationError(f"{folder}: not a SensorsCalibration calibration folder (needs extrinsic/ and "
                               "intrinsic/ subfolders)")
    spec_path, spec = _read_spec(folder)
    extrinsic = {p.stem: p for p in sorted((folder / "extrinsic").glob("*.json"))}
    if not extrinsic:
        raise CalibrationError(f"{folder / 'extrinsic'}: no camera's .json file")
    depths = _depths(spec["ground_depth"], list(extrinsic), str(spec_path))
    width, height, d, cx, cy = _bev_camera(spec["bev_camera"], str(spec_path))
    x0, y0 = _pair(spec.get("bev_center", [0.0, 0.0]), 2, f"{spec_path}: bev_center")
    ego_box = None
    if spec.get("ego_box") is not None:
        x_min, x_max, y_min, y_max = _pair(spec["ego_box"], 4, f"{spec_path}: ego_box")
        ego_box = (x_min, x_max, y_min, y_max)
    H = sum(depths.values()) / len(depths)
    T_VG = make_transform(R_VEHICLE_BEV, torch.tensor([x0, y0, H], dtype=torch.float64))
    cameras = {}
    for name, h in depths.items():
        intrinsic = folder / "intrinsic" / f"{name}.json"
        if not intrinsic.is_file():
            raise CalibrationError(f"{extrinsic[name]}: camera {name!r} has no {intrinsic}")
        try:
            model = OCamFisheye.from_json(intrinsic, max_fov_deg=max_fov_deg)
        except ValueError as e:
            raise CalibrationError(str(e)) from None
        T_CG = _read_T_CG(extrinsic[name])
        try:
            R, correction = nearest_rotation(T_CG[:3, :3].numpy())
        except ValueError as e:
            raise CalibrationError(f"{extrinsic[name]}: T_CG rotation is {e}") from None
        T_CG = make_transform(torch.from_numpy(R), T_CG[:3, 3] * (H / h))
        cameras[name] = RigCamera(name, model, T_VG @ invert_transform(T_CG))
        cameras[name].rotation_correction = correction
    s = d * H
    bev = BEVSpec(width, height, s, x0 - ((height - 1) / 2 - cy) * s, y0 - ((width - 1) / 2 - cx) * s, ego_box)
    return Rig(cameras, bev)
