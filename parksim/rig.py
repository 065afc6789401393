"""Surround-view rig: named cameras with their pose on the vehicle, and the BEV spec.

A rig file is JSON or YAML (by suffix) holding ``cameras: {name: {intrinsics, T_vehicle_camera}}``
and ``bev``; a rotation written in float32 or with 6 decimals is projected to the nearest proper rotation
(``parksim.geometry.nearest_rotation``), with a warning naming the largest correction. Importers read OpenCV
fisheye YAML files (K, D, resolution) and WoodScape calibration JSON (quaternion + translation extrinsics in
ISO 8855, radial_poly intrinsics).
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from .camera import CameraModel, OpenCVFisheye, RadialPolyFisheye, camera_from_dict
from .geometry import make_transform, nearest_rotation, rotation_from_quaternion

__all__ = ["BEVSpec", "RigCamera", "Rig", "CalibrationError", "read_opencv_yaml"]


class CalibrationError(ValueError):
    """A calibration or rig file is missing, malformed or inconsistent; the message names it."""


@dataclass(frozen=True)
class BEVSpec:
    """Vehicle-centred bird's-eye view: x forward is image up, y left is image left.

    ``center_x, center_y`` is the vehicle-frame ground point at the image centre, ``m_per_px``
    the ground sampling distance; ``ego_box = (x_min, x_max, y_min, y_max)`` in the vehicle
    frame is masked (the car itself). DMPR-PS uses 600 px = 10 m.

    Attributes:
        width: BEV image width in pixels.
        height: BEV image height in pixels.
        m_per_px: ground sampling distance in metres per pixel.
        center_x: vehicle-frame x (m) at the image centre.
        center_y: vehicle-frame y (m) at the image centre.
        ego_box: ``(x_min, x_max, y_min, y_max)`` in metres, masked out; None masks nothing.

    Raises:
        CalibrationError: a non-positive size or ``m_per_px``, or an ``ego_box`` of other than 4 numbers.
    """

    width: int = 600
    height: int = 600
    m_per_px: float = 10.0 / 600
    center_x: float = 0.0
    center_y: float = 0.0
    ego_box: tuple[float, float, float, float] | None = None

    def __post_init__(self) -> None:
        """Check the size and scale; store ``ego_box`` as a tuple of floats."""
        if self.width <= 0 or self.height <= 0 or not self.m_per_px > 0:
            raise CalibrationError(f"BEV spec needs positive size and m_per_px, got {self}")
        if self.ego_box is not None:
            object.__setattr__(self, "ego_box", tuple(float(v) for v in self.ego_box))
            if len(self.ego_box) != 4:
                raise CalibrationError(f"ego_box must be (x_min, x_max, y_min, y_max), got {self.ego_box}")

    @property
    def K_ipm(self) -> Tensor:
        """3x3 map from vehicle ground ``[x, y, 1]`` to BEV pixel ``[u, v, 1]`` (the paper's K_ipm)."""
        s = 1.0 / self.m_per_px
        u0 = (self.width - 1) / 2 + self.center_y * s
        v0 = (self.height - 1) / 2 + self.center_x * s
        return torch.tensor([[0.0, -s, u0], [-s, 0.0, v0], [0.0, 0.0, 1.0]], dtype=torch.float64)

    def pixel_to_ground(self, uv: Tensor) -> Tensor:
        """BEV pixels ``[...,2]`` -> vehicle-frame ground ``[...,2]`` (x, y).

        Args:
            uv: ``[..., 2]`` BEV pixels as (column, row), pixel centres at integers.

        Returns:
            ``[..., 2]`` ground points (x, y) in metres, vehicle frame.
        """
        u, v = uv[..., 0], uv[..., 1]
        x = self.center_x - (v - (self.height - 1) / 2) * self.m_per_px
        y = self.center_y - (u - (self.width - 1) / 2) * self.m_per_px
        return torch.stack([x, y], dim=-1)

    def ground_to_pixel(self, xy: Tensor) -> Tensor:
        """Vehicle-frame ground ``[...,2]`` -> BEV pixels ``[...,2]``.

        Args:
            xy: ``[..., 2]`` ground points (x, y) in metres, vehicle frame.

        Returns:
            ``[..., 2]`` BEV pixels as (column, row); the inverse of ``pixel_to_ground``.
        """
        u = (self.width - 1) / 2 - (xy[..., 1] - self.center_y) / self.m_per_px
        v = (self.height - 1) / 2 - (xy[..., 0] - self.center_x) / self.m_per_px
        return torch.stack([u, v], dim=-1)

    def to_dict(self) -> dict[str, Any]:
        """The fields as plain JSON values, read back by ``from_dict``.

        Returns:
            ``{field: value}`` with ``ego_box`` a list or None.
        """
        return {"width": self.width, "height": self.height, "m_per_px": self.m_per_px,
                "center_x": self.center_x, "center_y": self.center_y,
                "ego_box": list(self.ego_box) if self.ego_box is not None else None}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> BEVSpec:
        """The spec from ``to_dict``'s mapping; missing keys take the defaults.

        Args:
            d: a subset of the fields' names to values.

        Returns:
            The spec.

        Raises:
            CalibrationError: an unknown key, or values the spec refuses.
        """
        unknown = set(d) - {"width", "height", "m_per_px", "center_x", "center_y", "ego_box"}
        if unknown:
            raise CalibrationError(f"unknown BEV spec keys {sorted(unknown)}")
        return cls(**d)


@dataclass
class RigCamera:
    """One camera of the rig: its lens model and ``T_vehicle_camera`` (4x4, float64).

    Attributes:
        name: the camera's name in the rig.
        model: its lens model (intrinsics).
        T_vehicle_camera: ``(4, 4)`` float64 camera -> vehicle transform (OpenCV camera axes), its rotation
            projected to the nearest proper rotation (``parksim.geometry.nearest_rotation``).
        rotation_correction: the largest entry that projection changed (0.0: the rotation was exact, kept bit
            for bit).

    Raises:
        CalibrationError: ``T_vehicle_camera`` is not a finite 4x4 whose rotation is a proper rotation within
            ``parksim.geometry.ROTATION_TOLERANCE``.
    """

    name: str
    model: CameraModel
    T_vehicle_camera: Tensor
    rotation_correction: float = field(default=0.0, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        """Check ``T_vehicle_camera``, project its rotation and store it as a float64 tensor."""
        T = torch.as_tensor(self.T_vehicle_camera, dtype=torch.float64)
        if T.shape != (4, 4) or not torch.isfinite(T).all():
            raise CalibrationError(f"camera {self.name!r}: T_vehicle_camera must be a finite 4x4 matrix")
        try:
            R, self.rotation_correction = nearest_rotation(T[:3, :3].detach().cpu().numpy())
        except ValueError as e:
            raise CalibrationError(f"camera {self.name!r}: T_vehicle_camera rotation is {e}") from None
        if self.rotation_correction:
            T = T.detach().clone()
            T[:3, :3] = torch.from_numpy(R).to(T.device)
        self.T_vehicle_camera = T


@dataclass
class Rig:
    """Named cameras (insertion order kept) and the BEV spec.

    Attributes:
        cameras: ``{name: RigCamera}``; the order is the render order.
        bev: the bird's-eye view that ``parksim.ipm.IPM`` and ``render(..., bev=True)`` produce.
    """

    cameras: dict[str, RigCamera]
    bev: BEVSpec = field(default_factory=BEVSpec)

    @property
    def names(self) -> list[str]:
        """Camera names in rig order."""
        return list(self.cameras)

    def to_dict(self) -> dict[str, Any]:
        """The rig file's content, read back by ``from_dict``.

        Returns:
            ``{"cameras": {name: {"intrinsics": {...}, "T_vehicle_camera": 4x4 list}}, "bev": {...}}``.
        """
        return {"cameras": {n: {"intrinsics": c.model.to_dict(),
                                "T_vehicle_camera": c.T_vehicle_camera.tolist()}
                            for n, c in self.cameras.items()},
                "bev": self.bev.to_dict()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: str = "rig") -> Rig:
        """The rig from ``to_dict``'s mapping.

        Args:
            d: ``{"cameras": {name: {"intrinsics": ..., "T_vehicle_camera": 4x4}}, "bev": {...}}``.
            source: what to name in error messages (the file it came from).

        Returns:
            The rig, cameras in the mapping's order; a warning names the largest rotation projected
            (``RigCamera.rotation_correction``) when a rotation was not exact.

        Raises:
            CalibrationError: no cameras, a camera whose intrinsics or transform are refused, or a bad BEV spec.
        """
        if not isinstance(d, Mapping) or not isinstance(d.get("cameras"), Mapping) or not d["cameras"]:
            raise CalibrationError(f"{source}: expected a mapping with a non-empty 'cameras' mapping")
        cams = {}
        for name, c in d["cameras"].items():
            try:
                model = camera_from_dict(c["intrinsics"])
                cams[name] = RigCamera(name, model, torch.tensor(c["T_vehicle_camera"], dtype=torch.float64))
            except (KeyError, TypeError, ValueError, RuntimeError) as e:
                raise CalibrationError(f"{source}: camera {name!r}: {e}") from None
        try:
            bev = BEVSpec.from_dict(d.get("bev") or {})
        except TypeError as e:
            raise CalibrationError(f"{source}: bad BEV spec: {e}") from None
        corrected = {n: c.rotation_correction for n, c in cams.items() if c.rotation_correction}
        if corrected:
            worst = max(corrected, key=corrected.__getitem__)
            warnings.warn(f"{source}: T_vehicle_camera of {len(corrected)} camera(s) projected to the nearest proper "
                          f"rotation (largest correction {corrected[worst]:.2g}, camera {worst!r})", stacklevel=2)
        return cls(cams, bev)

    def save(self, path: str | Path) -> None:
        """Write JSON (``.json``) or YAML (``.yaml``/``.yml``).

        Args:
            path: the file; YAML for a ``.yaml``/``.yml`` suffix, JSON otherwise.
        """
        path = Path(path)
        d = self.to_dict()
        if path.suffix in (".yaml", ".yml"):
            import yaml
            text = yaml.safe_dump(d, sort_keys=False)
        else:
            text = json.dumps(d, indent=2)
        path.write_text(text)

    @classmethod
    def load(cls, path: str | Path) -> Rig:
        """Read a rig file that ``save`` wrote.

        Args:
            path: JSON or YAML (by suffix) rig file.

        Returns:
            The rig.

        Raises:
            CalibrationError: the file is missing, does not parse, or holds a rig ``from_dict`` refuses.
        """
        path = Path(path)
        if not path.is_file():
            raise CalibrationError(f"{path}: rig file not found")
        text = path.read_text()
        try:
            if path.suffix in (".yaml", ".yml"):
                import yaml
                d = yaml.safe_load(text)
            else:
                d = json.loads(text)
        except Exception as e:  # the parsers raise many types; all mean the same here
            raise CalibrationError(f"{path}: cannot parse rig file: {e}") from None
        return cls.from_dict(d, source=str(path))

    @classmethod
    def from_opencv_yaml(cls, paths: Mapping[str, str | Path], T_vehicle_camera: Mapping[str, Tensor],
                         bev: BEVSpec | None = None, max_fov_deg: float = 190.0) -> Rig:
        """Cameras from OpenCV fisheye YAML files (``camera_matrix``, ``dist_coeffs``, ``resolution``).

        Those files carry no extrinsics, so each camera's ``T_vehicle_camera`` is given
        (see ``parksim.calib.sample_rig`` to recover them from ground homographies).

        Args:
            paths: ``{camera name: YAML file}``.
            T_vehicle_camera: ``{camera name: (4, 4) camera -> vehicle transform}`` for every camera in ``paths``.
            bev: the BEV spec (default ``BEVSpec()``).
            max_fov_deg: full field of view of every lens, in degrees.

        Returns:
            The rig, cameras in ``paths``' order.

        Raises:
            CalibrationError: a camera without a transform, or a file ``read_opencv_yaml`` refuses.
        """
        cams = {}
        for name, p in paths.items():
            if name not in T_vehicle_camera:
                raise CalibrationError(f"no T_vehicle_camera given for camera {name!r}")
            calib = read_opencv_yaml(p)
            width, height = (int(v) for v in calib["resolution"].reshape(-1))
            model = OpenCVFisheye.from_K_D(calib["camera_matrix"], calib["dist_coeffs"], (width, height), max_fov_deg)
            cams[name] = RigCamera(name, model, T_vehicle_camera[name])
        return cls(cams, bev or BEVSpec())

    @classmethod
    def from_woodscape(cls, paths: Mapping[str, str | Path] | list[str | Path], bev: BEVSpec | None = None,
                       max_fov_deg: float = 190.0) -> Rig:
        """Cameras from WoodScape calibration JSON files; names come from the files' ``name`` unless given.

        WoodScape's vehicle frame is ISO 8855 on the ground under the rear-axle centre, the
        camera frame is OpenCV's, and (quaternion (x, y, z, w), translation) is camera -> vehicle:
        exactly our ``T_vehicle_camera``, so no axis change is needed.

        Args:
            paths: calibration JSON files, as a list or as ``{camera name: file}``.
            bev: the BEV spec (default ``BEVSpec()``).
            max_fov_deg: full field of view of every lens, in degrees.

        Returns:
            The rig, cameras in ``paths``' order.

        Raises:
            CalibrationError: a file that is missing, not JSON, lacks a key, names another camera model, or holds
                a bad value; the message names the file.
        """
        items = paths.items() if isinstance(paths, Mapping) else [(None, p) for p in paths]
        cams = {}
        for given, p in items:
            p = Path(p)
            try:
                d = json.loads(p.read_text())
            except FileNotFoundError:
                raise CalibrationError(f"WoodScape calibration not found: {p}") from None
            except json.JSONDecodeError as e:
                raise CalibrationError(f"{p}: not valid JSON: {e}") from None
            try:
                intr, extr = d["intrinsic"], d["extrinsic"]
                if intr["model"] != "radial_poly":
                    raise CalibrationError(f"{p}: unknown camera model {intr['model']!r}; "
                                           "WoodScape files use 'radial_poly'")
                model = RadialPolyFisheye(int(intr["width"]), int(intr["height"]),
                                          [intr["k1"], intr["k2"], intr["k3"], intr["k4"]],
                                          intr["cx_offset"], intr["cy_offset"], intr["aspect_ratio"], max_fov_deg)
                qx, qy, qz, qw = (float(v) for v in extr["quaternion"])
                t = torch.tensor([float(v) for v in extr["translation"]], dtype=torch.float64)
                if t.numel() != 3 or not torch.isfinite(t).all():
                    raise CalibrationError(f"{p}: extrinsic translation must be 3 finite numbers")
                if not all(math.isfinite(v) for v in (qx, qy, qz, qw)) or qx == qy == qz == qw == 0:
                    raise CalibrationError(f"{p}: extrinsic quaternion must be finite and non-zero")
                R = rotation_from_quaternion(torch.tensor([qw, qx, qy, qz], dtype=torch.float64))
                name = given or d.get("name") or p.stem
            except KeyError as e:
                raise CalibrationError(f"{p}: missing key {e.args[0]!r} in WoodScape calibration") from None
            except CalibrationError:
                raise
            except (TypeError, ValueError) as e:
                raise CalibrationError(f"{p}: bad value in WoodScape calibration: {e}") from None
            cams[name] = RigCamera(name, model, make_transform(R, t))
        return cls(cams, bev or BEVSpec())


def read_opencv_yaml(path: str | Path) -> dict[str, Any]:
    """Read an OpenCV ``FileStorage`` YAML into ``{key: ndarray}``; errors name the file and key.

    Args:
        path: the YAML file (``camera_matrix``, ``dist_coeffs``, ``resolution``, possibly more).

    Returns:
        Every key of the file as a float64 array (a scalar node as a float); ``camera_matrix`` reshaped to
        ``(3, 3)``, ``dist_coeffs`` to ``(4,)`` and ``resolution`` to ``(2,)`` as (width, height).

    Raises:
        CalibrationError: the file is missing or unreadable, or one of the three keys is missing or holds the
            wrong number of finite values.
    """
    import cv2
    import numpy as np

    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"calibration file not found: {path}")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as e:  # OpenCV's parser errors surface as either
        raise CalibrationError(f"{path}: not a readable OpenCV YAML file ({str(e).strip().splitlines()[-1]})") from None
    if not fs.isOpened():
        raise CalibrationError(f"{path}: not a readable OpenCV YAML file")
    out: dict[str, Any] = {}
    root = fs.root()
    for key in root.keys():
        node = fs.getNode(key)
        mat = node.mat()
        out[key] = np.asarray(mat, dtype=np.float64) if mat is not None else node.real()
    fs.release()
    expected = {"camera_matrix": (3, 3), "dist_coeffs": (4,), "resolution": (2,)}
    for key, shape in expected.items():
        if key not in out:
            raise CalibrationError(f"{path}: missing {key!r}")
        arr = np.asarray(out[key], dtype=np.float64)
        if arr.size != int(np.prod(shape)) or not np.isfinite(arr).all():
            raise CalibrationError(f"{path}: {key!r} must hold {int(np.prod(shape))} finite numbers, "
                                   f"got {arr.ravel().tolist()}")
        out[key] = arr.reshape(shape)
    return out
