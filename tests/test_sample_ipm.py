"""The real surround-view sample: recovered poses, our IPM against the sample's own calibration, square sizes, seams.

The oracle for (a) is the sample's own pipeline run with OpenCV, independent of our code:
``cv2.fisheye.initUndistortRectifyMap`` (with its scaled/shifted camera matrix), its homography
(``warpPerspective``) and its flips, applied to an image that holds each pixel's fisheye
coordinates, so every stitched bird's-eye pixel carries the fisheye pixel the calibration implies.
"""


import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from parksim.assets import SAMPLE_DIR as SAMPLE
from parksim.calib.sample_rig import load_sample_images, sample_rig
from parksim.ipm import IPM

# The sample's stitched bird's-eye layout (1 cm/px): 1200 x 1600, pattern inset by 300, car strips.
W, H, SHIFT, XL, YT = 1200, 1600, 300, 500, 550
STEMS = {"front": "front", "back": "rear", "left": "left", "right": "right"}


@pytest.fixture(scope="module")
def sample():
    rig, report = sample_rig(SAMPLE, m_per_px=0.01)
    ipm = IPM(rig)
    images = load_sample_images(SAMPLE, rig)
    return rig, report, ipm, images


def implied_fisheye_coords(stem: str) -> np.ndarray:
    """HxWx3 stitched image of (u, v, coverage) from the sample's own OpenCV pipeline."""
    fs = cv2.FileStorage(str(SAMPLE / "yaml" / f"{stem}.yaml"), cv2.FILE_STORAGE_READ)
    K, D = fs.getNode("camera_matrix").mat(), fs.getNode("dist_coeffs").mat()
    scale, shift = fs.getNode("scale_xy").mat().ravel(), fs.getNode("shift_xy").mat().ravel()
    Hm = fs.getNode("project_matrix").mat()
    w, h = (int(v) for v in fs.getNode("resolution").mat().ravel())
    K_new = K.copy()
    K_new[0, 0] *= scale[0]
    K_new[1, 1] *= scale[1]
    K_new[0, 2] += shift[0]
    K_new[1, 2] += shift[1]
    mu, mv = cv2.fisheye.initUndistortRectifyMap(K, D, np.eye(3), K_new, (w, h), cv2.CV_32FC1)
    coords = np.dstack([mu, mv, np.ones_like(mu)])
    shape = (W, YT) if stem in ("front", "back") else (H, XL)
    proj = cv2.warpPerspective(coords, Hm, shape, flags=cv2.INTER_LINEAR, borderValue=0)
    full = np.zeros((H, W, 3), np.float32)
    if stem == "front":
        full[:YT] = proj
    elif stem == "back":
        full[H - YT:] = proj[::-1, ::-1]
    elif stem == "left":
        full[:, :XL] = cv2.transpose(proj)[::-1]
    else:
        full[:, W - XL:] = np.flip(cv2.transpose(proj), 1)
    return full


def test_recovered_poses_fit_the_homographies(sample):
    rig, report, _, _ = sample
    heights = {n: float(c.T_vehicle_camera[2, 3]) for n, c in rig.cameras.items()}
    assert all(0.4 < z < 1.5 for z in heights.values()), heights       # cameras sit on the car
    assert rig.cameras["front"].T_vehicle_camera[0, 2] > 0.8            # optical axes point outwards
    assert rig.cameras["rear"].T_vehicle_camera[0, 2] < -0.7
    assert rig.cameras["left"].T_vehicle_camera[1, 2] > 0.5
    assert rig.cameras["right"].T_vehicle_camera[1, 2] < -0.5
    for name, r in report.items():
        print(f"{name}: rigid fit median {r['median_px']:.2f} px, max {r['max_px']:.2f} px; homography axes "
              f"ratio {r['axis_ratio']:.3f}, angle {r['axis_angle_deg']:.1f} deg")
        assert r["median_px"] < 2.5


def test_ipm_samples_where_the_sample_calibration_points(sample):
    """(a) Over the ground pattern, the fisheye pixel our IPM samples vs the calibration's own."""
    rig, _, ipm, _ = sample
    yy, xx = np.mgrid[0:H, 0:W]
    pattern = (xx >= SHIFT) & (xx <= W - SHIFT) & (yy >= SHIFT) & (yy <= H - SHIFT)
    for stem, name in STEMS.items():
        oracle = implied_fisheye_coords(stem)
        sel = pattern & (oracle[..., 2] > 0.999)
        # Stitched pixel (bx, by) is ground ((800 - by) cm, (600 - bx) cm) = our BEV pixel (bx - 0.5, by - 0.5).
        grid = torch.from_numpy(np.stack([(xx[sel] - 0.5) / (W - 1) * 2 - 1, (yy[sel] - 0.5) / (H - 1) * 2 - 1],
                                         -1)).float()[None, None]
        ours = F.grid_sample(ipm.pixel_coords[name].permute(2, 0, 1)[None].float(), grid,
                             align_corners=True)[0, :, 0].T.numpy()
        sees = F.grid_sample((ipm.weights[name] > 0).float()[None, None], grid,
                             align_corners=True)[0, 0, 0].numpy() > 0.999
        err = np.linalg.norm(ours - oracle[sel][:, :2], axis=-1)[sees]
        print(f"{name}: {len(err)} pattern pixels, median {np.median(err):.2f} px, "
              f"p95 {np.percentile(err, 95):.2f} px, max {err.max():.2f} px")
        assert len(err) > 50000
        assert np.median(err) < 3.0


def x_corners(gray: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Checkerboard X-junctions: corners whose 8 cm ring alternates dark/bright four times."""
    pts = cv2.goodFeaturesToTrack(gray, 3000, 0.02, 12, mask=mask, blockSize=9)
    pts = cv2.cornerSubPix(gray, pts.astype(np.float32), (7, 7), (-1, -1),
                           (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 0.01))[:, 0]
    ang = np.linspace(0, 2 * np.pi, 32, endpoint=False)
    keep = []
    for p in pts:
        xs = np.clip((p[0] + 8 * np.cos(ang)).round().astype(int), 0, gray.shape[1] - 1)
        ys = np.clip((p[1] + 8 * np.sin(ang)).round().astype(int), 0, gray.shape[0] - 1)
        ring = gray[ys, xs].astype(float)
        bright = ring > (ring.max() + ring.min()) / 2
        keep.append(ring.max() - ring.min() > 60 and np.sum(bright != np.roll(bright, 1)) == 4)
    return pts[np.array(keep)]


def test_pattern_squares_measure_40_cm(sample):
    """(b) Neighbouring X-corners of the checkerboard are one 40 cm square apart in our 1 cm/px BEV."""
    rig, _, ipm, images = sample
    bev = (ipm(images).numpy() * 255).round().astype(np.uint8)
    gray = cv2.cvtColor(bev, cv2.COLOR_RGB2GRAY)
    mask = ipm.mask.numpy().astype(np.uint8)
    region = np.zeros_like(mask)
    region[SHIFT:H - SHIFT + 1, SHIFT:W - SHIFT + 1] = 1
    region[YT - 60:H - YT + 60, XL - 60:W - XL + 60] = 0  # the car body mirrored next to the car
    corners = x_corners(gray, cv2.erode(region & mask, np.ones((15, 15), np.uint8)))
    lengths = []
    for c in corners:
        for axis in (0, 1):
            d = corners - c
            ok = (d[:, axis] > 25) & (d[:, axis] < 60) & (np.abs(d[:, 1 - axis]) < 0.18 * d[:, axis])
            if ok.any():
                lengths.append(np.linalg.norm(d[ok], axis=1).min())
    lengths = np.array(lengths) * rig.bev.m_per_px * 100
    print(f"{len(corners)} X-corners, {len(lengths)} square edges: median {np.median(lengths):.2f} cm, "
          f"p10 {np.percentile(lengths, 10):.1f} cm, p90 {np.percentile(lengths, 90):.1f} cm")
    assert len(lengths) > 100
    assert abs(np.median(lengths) - 40.0) < 2.0


def test_seam_misalignment_is_reported(sample):
    """(c) Offset between neighbouring cameras' BEVs at the pattern's four corners, in cm (not pass/fail)."""
    rig, _, _, images = sample
    single = {n: cv2.cvtColor(IPM(rig, cameras=[n])({n: images[n]}).numpy(), cv2.COLOR_RGB2GRAY) for n in rig.names}
    corners = {("front", "left"): (300, 300), ("front", "right"): (300, 700),
               ("rear", "left"): (1060, 300), ("rear", "right"): (1060, 700)}
    search = 15  # cm: less than half a square, so the checkerboard's period cannot alias
    offsets = {}
    for (a, b), (r0, c0) in corners.items():
        patch = single[a][r0 + search:r0 + 240 - search, c0 + search:c0 + 200 - search]
        area = single[b][r0:r0 + 240, c0:c0 + 200]
        score = cv2.matchTemplate(area, patch, cv2.TM_CCOEFF_NORMED)
        _, best, _, (px, py) = cv2.minMaxLoc(score)
        offsets[(a, b)] = float(np.hypot(px - search, py - search)) * rig.bev.m_per_px * 100
        print(f"seam {a}/{b}: {px - search:+d} cm x {py - search:+d} cm (|{offsets[(a, b)]:.1f}| cm), "
              f"correlation {best:.2f}")
        offsets[(a, b)] = (offsets[(a, b)], best)
    # The left camera sees the rear-left corner at grazing angles near its lens edge, where the sample's
    # intrinsics bend the pattern (correlation ~0.3): reported, not judged. Well-observed seams agree closely.
    good = [off for off, corr in offsets.values() if corr > 0.5]
    assert len(good) >= 3
    assert max(good) < 5.0
