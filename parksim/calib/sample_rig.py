"""Turn the real surround-view sample (OpenCV fisheye YAML + ground homographies) into a ``Rig``.

The sample (shipped as ``parksim/assets/surround-view-sample``) has intrinsics but no extrinsics: each
camera instead carries ``project_matrix``, a homography from its undistorted image (camera
matrix scaled by ``scale_xy`` and shifted by ``shift_xy``) to a bird's-eye image of the
6 m x 10 m ground pattern at 1 cm/px. Those homographies are not exactly rigid, so each
camera's pose is the rigid pose whose fisheye projection best reproduces the homography's
ground-to-fisheye mapping over the pattern (Levenberg-Marquardt on pixel residuals),
started from a direct decomposition of the homography.

The sample's vehicle frame has its origin at the pattern centre (the car's centre; the
data has no rear-axle position), x forward, y left, z up.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from ..camera import OpenCVFisheye
from ..geometry import invert_transform, make_transform
from ..rig import BEVSpec, CalibrationError, Rig, RigCamera, read_opencv_yaml

__all__ = ["SAMPLE_CAMERAS", "SampleLayout", "SampleCamera", "load_sample_cameras", "fit_camera_pose",
           "sample_rig", "sample_bev_spec", "load_sample_images"]

# File stem in the sample -> our rig name.
SAMPLE_CAMERAS = {"front": "front", "back": "rear", "left": "left", "right": "right"}


@dataclass(frozen=True)
class SampleLayout:
    """The sample's stitched bird's-eye image: 1 cm/px, pattern 600 x 1000 px, car in the middle.

    Each camera's homography maps into its own projected image, which is flipped/transposed
    into the stitched image (front as is, back rotated 180 deg, left and right transposed).
    """

    width: int = 1200
    height: int = 1600
    shift: int = 300          # margin around the pattern, px
    car_x: int = 500          # left edge of the car region, px (= width of the left strip)
    car_y: int = 550          # top edge of the car region, px (= height of the front strip)
    m_per_px: float = 0.01

    @property
    def pattern_m(self) -> tuple[float, float]:
        """Pattern length (x, forward) and width (y) in metres."""
        return ((self.height - 2 * self.shift) * self.m_per_px, (self.width - 2 * self.shift) * self.m_per_px)

    @property
    def ego_box(self) -> tuple[float, float, float, float]:
        """The car's footprint ``(x_min, x_max, y_min, y_max)`` in the vehicle frame."""
        hx = (self.height / 2 - self.car_y) * self.m_per_px
        hy = (self.width / 2 - self.car_x) * self.m_per_px
        return (-hx, hx, -hy, hy)

    def ground_to_bird(self, xy: Tensor) -> Tensor:
        """Vehicle ground (x, y) -> stitched-image pixel (column, row)."""
        return torch.stack([self.width / 2 - xy[..., 1] / self.m_per_px,
                            self.height / 2 - xy[..., 0] / self.m_per_px], dim=-1)

    def bird_to_projected(self, name: str, b: Tensor) -> Tensor:
        """Stitched-image pixel -> pixel of camera ``name``'s own projected image (undoes its flip)."""
        bx, by = b[..., 0], b[..., 1]
        W, H = self.width, self.height
        if name == "front":
            p = (bx, by)
        elif name == "back":
            p = (W - 1 - bx, H - 1 - by)
        elif name == "left":
            p = (H - 1 - by, bx)
        elif name == "right":
            p = (by, W - 1 - bx)
        else:
            raise ValueError(f"unknown sample camera {name!r}; expected one of {list(SAMPLE_CAMERAS)}")
        return torch.stack(p, dim=-1)

    def in_strip(self, name: str, b: Tensor) -> Tensor:
        """Whether a stitched-image pixel lies in the strip that camera ``name`` fills."""
        bx, by = b[..., 0], b[..., 1]
        return {"front": by < self.car_y, "back": by >= self.height - self.car_y,
                "left": bx < self.car_x, "right": bx >= self.width - self.car_x}[name]

    def pattern_points(self, step_m: float = 0.05) -> Tensor:
        """Ground points (x, y) on a regular grid over the pattern, outside the car."""
        lx, ly = self.pattern_m
        xs = torch.arange(-lx / 2, lx / 2 + 1e-9, step_m, dtype=torch.float64)
        ys = torch.arange(-ly / 2, ly / 2 + 1e-9, step_m, dtype=torch.float64)
        gx, gy = torch.meshgrid(xs, ys, indexing="ij")
        xy = torch.stack([gx, gy], dim=-1).reshape(-1, 2)
        x0, x1, y0, y1 = self.ego_box
        car = (xy[:, 0] > x0) & (xy[:, 0] < x1) & (xy[:, 1] > y0) & (xy[:, 1] < y1)
        return xy[~car]


@dataclass
class SampleCamera:
    """One sample camera: its lens, the undistortion camera matrix and its ground homography."""

    name: str
    model: OpenCVFisheye
    K_undistorted: Tensor   # camera matrix of the undistorted image the homography starts from
    homography: Tensor      # undistorted pixel -> projected bird's-eye pixel

    def rays_for_ground(self, layout: SampleLayout, xy: Tensor) -> tuple[Tensor, Tensor]:
        """Camera-frame ray (x/z, y/z, 1) the homography implies for ground points, and where it is defined."""
        b = layout.ground_to_bird(xy)
        p = layout.bird_to_projected(self.name, b)
        ph = torch.cat([p, torch.ones_like(p[..., :1])], dim=-1)
        und = ph @ torch.linalg.inv(self.homography).T
        rays = und @ torch.linalg.inv(self.K_undistorted).T
        # A homography is defined up to sign: the camera sees its own strip in front of it.
        strip = layout.in_strip(self.name, b)
        sign = torch.sign(rays[..., 2][strip].median()) if strip.any() else torch.sign(rays[..., 2].median())
        rays = rays * sign
        ok = rays[..., 2] > 1e-9
        rays = rays / torch.where(ok, rays[..., 2], torch.ones_like(rays[..., 2])).unsqueeze(-1)
        return rays, ok

    def implied_pixels(self, layout: SampleLayout, xy: Tensor) -> tuple[Tensor, Tensor]:
        """Fisheye pixels the sample's own calibration implies for ground points, and validity."""
        rays, ok = self.rays_for_ground(layout, xy)
        uv, valid = self.model.project(rays)
        return uv, ok & valid & layout.in_strip(self.name, layout.ground_to_bird(xy))


def load_sample_cameras(sample_dir: str | Path, max_fov_deg: float = 190.0) -> dict[str, SampleCamera]:
    """Read the four YAML files of the sample (front, back, left, right)."""
    sample_dir = Path(sample_dir)
    yaml_dir = sample_dir / "yaml"
    if not yaml_dir.is_dir():
        raise CalibrationError(f"{sample_dir}: expected a 'yaml' folder with front/back/left/right.yaml")
    cams = {}
    for stem in SAMPLE_CAMERAS:
        path = yaml_dir / f"{stem}.yaml"
        d = read_opencv_yaml(path)
        for key in ("project_matrix", "scale_xy", "shift_xy"):
            if key not in d:
                raise CalibrationError(f"{path}: missing {key!r} (the sample's ground homography)")
        K = torch.as_tensor(d["camera_matrix"], dtype=torch.float64)
        scale = torch.as_tensor(d["scale_xy"], dtype=torch.float64).reshape(-1)
        shift = torch.as_tensor(d["shift_xy"], dtype=torch.float64).reshape(-1)
        K_new = K.clone()
        K_new[0, 0] *= scale[0]
        K_new[1, 1] *= scale[1]
        K_new[0, 2] += shift[0]
        K_new[1, 2] += shift[1]
        width, height = (int(v) for v in d["resolution"].reshape(-1))
        model = OpenCVFisheye.from_K_D(K, d["dist_coeffs"], (width, height), max_fov_deg)
        H = torch.as_tensor(d["project_matrix"], dtype=torch.float64).reshape(3, 3)
        cams[stem] = SampleCamera(stem, model, K_new, H)
    return cams


def _rodrigues(w: Tensor) -> Tensor:
    """Rotation vector -> matrix, smooth at zero."""
    theta2 = (w * w).sum()
    K = torch.zeros(3, 3, dtype=w.dtype)
    K[0, 1], K[0, 2], K[1, 0], K[1, 2], K[2, 0], K[2, 1] = -w[2], w[1], w[2], -w[0], -w[1], w[0]
    small = theta2 < 1e-12
    theta = torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(1e-30))
    return torch.eye(3, dtype=w.dtype) + a * K + b * (K @ K)


def _decompose(G: Tensor, xy_ref: Tensor) -> tuple[Tensor, Tensor]:
    """Rigid ``(R, t)`` of camera <- ground from a plane homography ``G ~ [r1 r2 t]``."""
    lam = 2.0 / (G[:, 0].norm() + G[:, 1].norm())
    if (G @ torch.cat([xy_ref, torch.ones(1, dtype=G.dtype)]))[2] * lam < 0:
        lam = -lam
    r1, r2, t = lam * G[:, 0], lam * G[:, 1], lam * G[:, 2]
    R = torch.stack([r1, r2, torch.linalg.cross(r1, r2)], dim=1)
    U, _, Vh = torch.linalg.svd(R)
    R = U @ torch.diag(torch.tensor([1.0, 1.0, torch.det(U @ Vh).item()], dtype=G.dtype)) @ Vh
    return R, t


def fit_camera_pose(cam: SampleCamera, layout: SampleLayout, xy: Tensor,
                    iterations: int = 30) -> tuple[Tensor, dict[str, float]]:
    """Rigid ``T_vehicle_camera`` reproducing the homography's ground -> fisheye map in least squares.

    Returns the pose and a report: median/max pixel residual of the fit, and how far the
    homography is from rigid (ratio of its two ground-axis lengths, angle between them).
    """
    target, ok = cam.implied_pixels(layout, xy)
    pts, target = xy[ok], target[ok]
    if len(pts) < 20:
        raise CalibrationError(f"camera {cam.name!r}: only {len(pts)} pattern points map into its image")
    ground = torch.cat([pts, torch.zeros_like(pts[:, :1])], dim=-1)
    # Plane homography ground (x, y, 1) -> ray, fitted by DLT on the implied rays.
    rays, _ = cam.rays_for_ground(layout, pts)
    A = torch.zeros(2 * len(pts), 9, dtype=torch.float64)
    X = torch.cat([pts, torch.ones_like(pts[:, :1])], dim=-1)
    A[0::2, 0:3], A[0::2, 6:9] = X, -rays[:, :1] * X
    A[1::2, 3:6], A[1::2, 6:9] = X, -rays[:, 1:2] * X
    G = torch.linalg.svd(A, full_matrices=False).Vh[-1].reshape(3, 3)
    R0, t0 = _decompose(G, pts.mean(0))

    def residuals(params: Tensor) -> Tensor:
        R = _rodrigues(params[:3]) @ R0
        uv, _ = cam.model.project(ground @ R.T + (t0 + params[3:]))
        return (uv - target).reshape(-1)

    params = torch.zeros(6, dtype=torch.float64)
    damping = 1e-3
    cost = residuals(params).square().sum()
    for _ in range(iterations):
        J = torch.autograd.functional.jacobian(residuals, params, vectorize=True, strategy="forward-mode")
        r = residuals(params)
        JTJ, JTr = J.T @ J, J.T @ r
        while True:
            step = torch.linalg.solve(JTJ + damping * torch.diag(torch.diag(JTJ)), -JTr)
            new_cost = residuals(params + step).square().sum()
            if new_cost < cost:
                params, cost, damping = params + step, new_cost, max(damping / 3, 1e-9)
                break
            damping *= 4
            if damping > 1e8:
                break
        if step.norm() < 1e-12 or damping > 1e8:
            break
    R = _rodrigues(params[:3]) @ R0
    T_camera_vehicle = make_transform(R, t0 + params[3:])
    err = residuals(params).reshape(-1, 2).norm(dim=-1)
    a1, a2 = G[:, 0], G[:, 1]
    report = {"points": float(len(pts)), "median_px": float(err.median()), "max_px": float(err.max()),
              "axis_ratio": float(max(a1.norm(), a2.norm()) / min(a1.norm(), a2.norm())),
              "axis_angle_deg": float(torch.rad2deg(torch.arccos((a1 @ a2).abs() / (a1.norm() * a2.norm()))))}
    return invert_transform(T_camera_vehicle), report


def sample_bev_spec(layout: SampleLayout | None = None, m_per_px: float = 0.01) -> BEVSpec:
    """BEV covering the sample's stitched image (12 m x 16 m) at ``m_per_px``, car masked."""
    layout = layout or SampleLayout()
    scale = layout.m_per_px / m_per_px
    return BEVSpec(width=round(layout.width * scale), height=round(layout.height * scale), m_per_px=m_per_px,
                   center_x=0.0, center_y=0.0, ego_box=layout.ego_box)


def sample_rig(sample_dir: str | Path, m_per_px: float = 0.01,
               step_m: float = 0.1) -> tuple[Rig, dict[str, dict[str, float]]]:
    """The sample as a ``Rig`` (cameras named front/rear/left/right) and the per-camera fit report."""
    layout = SampleLayout()
    xy = layout.pattern_points(step_m)
    cameras, reports = {}, {}
    for stem, cam in load_sample_cameras(sample_dir).items():
        T, reports[SAMPLE_CAMERAS[stem]] = fit_camera_pose(cam, layout, xy)
        name = SAMPLE_CAMERAS[stem]
        cameras[name] = RigCamera(name, cam.model, T)
    return Rig(cameras, sample_bev_spec(layout, m_per_px)), reports


def load_sample_images(sample_dir: str | Path, rig: Rig) -> dict[str, Tensor]:
    """The sample's four PNGs as float32 RGB HxWx3 in [0, 1], keyed by rig camera name."""
    from ..imageio import read_image

    return {SAMPLE_CAMERAS[stem]: read_image(Path(sample_dir) / "images" / f"{stem}.png",
                                             expect_size=(rig.cameras[SAMPLE_CAMERAS[stem]].model.width,
                                                          rig.cameras[SAMPLE_CAMERAS[stem]].model.height))
            for stem in SAMPLE_CAMERAS}
