"""OCamFisheye against OCamCalib's own formulas, transcribed here in float64 numpy as the oracle.

The oracles work in OCamCalib's frame and pixel order: rays (x_o, y_o, z_o) = (y, x, -z) of ours and
pixels (row, column). ``ocam_world2cam`` and ``ocam_cam2world`` follow ``ocam_functions.c``;
``ocam_world2cam_exact`` follows the MATLAB toolbox's ``world2cam``/``omni3d2pixel`` (the smallest
positive real root of ``ss(rho) - (z / |xy|) rho``); ``avm_world2cam`` follows SensorsCalibration's
``run_avm.cpp`` for its JSON intrinsics (input (x, y, -z) of ours, output (column, row)).
"""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from parksim.camera import OCamFisheye, camera_from_dict

FIXTURES = Path(__file__).parent / "fixtures" / "ocam"
TXT = FIXTURES / "calib_results_bf_uv_fe.txt"      # BSD-3-Clause, ctu-mrs/uvdar_core
JSON = FIXTURES / "front_camera_intrinsic.json"     # Apache-2.0, PJLab-ADG/SensorsCalibration
# The fixture's numbers, as the file writes them.
SS = [-2.595395e+02, 0.0, 1.626945e-03, -2.328091e-06, 6.601777e-09]
INVPOL = [388.557547, 220.910537, -10.127377, 31.174444, 16.299989, 0.874110, 31.882430, 44.770601,
          21.586002, 3.593416]
XC, YC, C, D, E = 229.581672, 364.430465, 1.000314, -0.000012, -0.000158


def ocam_world2cam(p_o: np.ndarray, invpol, xc, yc, c, d, e) -> np.ndarray:
    """ocam_functions.c world2cam: OCam-frame points -> (row, column)."""
    x, y, z = p_o.T
    norm = np.sqrt(x * x + y * y)
    safe = np.where(norm != 0, norm, 1.0)
    theta = np.arctan(z / safe)
    rho, t_i = np.full_like(theta, invpol[0]), np.ones_like(theta)
    for coeff in invpol[1:]:
        t_i = t_i * theta
        rho = rho + t_i * coeff
    X, Y = x / safe * rho, y / safe * rho
    return np.where((norm != 0)[:, None], np.stack([X * c + Y * d + xc, X * e + Y + yc], -1), [xc, yc])


def ocam_cam2world(m: np.ndarray, ss, xc, yc, c, d, e) -> np.ndarray:
    """ocam_functions.c cam2world: (row, column) -> unit OCam-frame rays."""
    invdet = 1 / (c - d * e)
    xp = invdet * ((m[:, 0] - xc) - d * (m[:, 1] - yc))
    yp = invdet * (-e * (m[:, 0] - xc) + c * (m[:, 1] - yc))
    r = np.sqrt(xp * xp + yp * yp)
    zp, r_i = np.full_like(r, ss[0]), np.ones_like(r)
    for coeff in ss[1:]:
        r_i = r_i * r
        zp = zp + r_i * coeff
    v = np.stack([xp, yp, zp], -1)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def ocam_world2cam_exact(p_o: np.ndarray, ss, xc, yc, c, d, e) -> np.ndarray:
    """The MATLAB toolbox's world2cam: cam2world inverted through the roots of a polynomial."""
    out = []
    for x, y, z in p_o:
        norm = math.hypot(x, y)
        coeffs = np.array(ss[::-1], dtype=np.float64)
        coeffs[-2] -= z / norm
        roots = np.roots(coeffs)
        rho = roots[(roots.imag == 0) & (roots.real > 0)].real.min()
        X, Y = x / norm * rho, y / norm * rho
        out.append([X * c + Y * d + xc, X * e + Y + yc])
    return np.array(out)


def avm_world2cam(p: np.ndarray, K: np.ndarray, dist) -> np.ndarray:
    """SensorsCalibration run_avm.cpp world2cam, fed (x, y, -z) of our frame: -> (column, row)."""
    x, y, z = p[:, 0], p[:, 1], -p[:, 2]
    norm = np.sqrt(x * x + y * y)
    theta = np.arctan(z / norm)
    rho, t_i = np.full_like(theta, dist[0]), np.ones_like(theta)
    for coeff in dist[1:]:
        t_i = t_i * theta
        rho = rho + t_i * coeff
    X, Y = x / norm * rho, y / norm * rho
    return np.stack([X * K[0, 0] + Y * K[0, 1] + K[0, 2], X * K[1, 0] + Y + K[1, 2]], -1)


def to_ocam(p: np.ndarray) -> np.ndarray:
    return np.stack([p[:, 1], p[:, 0], -p[:, 2]], -1)


def directions(max_rad: float, n: int, seed: int) -> np.ndarray:
    """Unit rays from the axis to ``max_rad`` off it, all azimuths; the first is the axis itself."""
    rng = np.random.default_rng(seed)
    th = rng.uniform(0.0, max_rad, n)
    th[0], th[1] = 0.0, max_rad
    ph = rng.uniform(0, 2 * np.pi, n)
    return np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)


def angle_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    a, b = a / a.norm(dim=-1, keepdim=True), b / b.norm(dim=-1, keepdim=True)
    return torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1))


def txt_cam() -> OCamFisheye:
    return OCamFisheye.from_calib_results(TXT)


def variant(which: str) -> OCamFisheye:
    """The fixture lens from both polynomials ("both"), from "ss" or "invpol" alone; or the public "json" lens."""
    if which == "json":
        return OCamFisheye.from_json(JSON)
    args = {k: v for k, v in txt_cam().to_dict().items() if k != "model"}
    dropped = {"both": {}, "ss": {"invpol": None}, "invpol": {"ss": None}}[which]
    return OCamFisheye(**{**args, **dropped})


def json_from_txt(path: Path) -> None:
    """The fixture lens in SensorsCalibration's JSON form (see ocam.py: c' = 1/c, d' = e/c, e' = d/c,
    cam_dist = c invpol)."""
    K = [[1 / C, E / C, YC], [D / C, 1, XC], [0, 0, 1]]
    param = {"img_dist_w": 752, "img_dist_h": 480, "cam_K": {"rows": 3, "cols": 3, "data": K},
             "cam_dist": {"rows": 1, "cols": len(INVPOL), "data": [[v * C for v in INVPOL]]}}
    path.write_text(json.dumps({"front_camera-intrinsic": {"param": param}}))


def test_fixture_loads_with_ocamcalib_conventions():
    cam = txt_cam()
    assert (cam.width, cam.height, cam.by_ss) == (752, 480, True)
    assert cam.k.tolist() == SS and cam.other.tolist() == INVPOL
    # The axis lands on the centre: column yc, row xc.
    uv, valid = cam.project(torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64))
    assert uv.tolist() == [[YC, XC]] and valid.item()
    # Valid to the farthest image corner (~108.7 deg), where the calibration ends.
    assert 1.89 < cam.theta_max < 1.90
    one = OCamFisheye.from_calib_results(TXT, one_based=True)
    assert (float(one.cx), float(one.cy)) == (YC - 1, XC - 1)


def test_project_is_the_exact_inverse_of_cam2world_from_axis_to_valid_angle():
    cam = txt_cam()
    p = directions(cam.theta_max, 3000, seed=1)
    uv, _ = cam.project(torch.from_numpy(p * np.random.default_rng(2).uniform(0.2, 50.0, (len(p), 1))))
    rc = uv.numpy()[:, ::-1]
    # cam2world of our pixel gives the ray back: project is ss's exact inverse ...
    back = torch.from_numpy(ocam_cam2world(rc, SS, XC, YC, C, D, E))
    assert angle_between(back, torch.from_numpy(to_ocam(p))).max() < 1e-12
    # ... the very pixel the MATLAB toolbox's exact world2cam gives (axis excluded: it has no azimuth there) ...
    exact = ocam_world2cam_exact(to_ocam(p[1:]), SS, XC, YC, C, D, E)
    assert np.abs(rc[1:] - exact).max() < 1e-9
    # ... and within the invpol fit's error of the C world2cam, which is that fit.
    fit = np.abs(ocam_world2cam(to_ocam(p[1:]), INVPOL, XC, YC, C, D, E) - exact).max()
    assert np.abs(rc[1:] - ocam_world2cam(to_ocam(p[1:]), INVPOL, XC, YC, C, D, E)).max() <= fit + 1e-9
    assert 1e-4 < fit < 0.1


def test_unproject_matches_cam2world_over_the_image():
    cam = txt_cam()
    rng = np.random.default_rng(3)
    uv = torch.from_numpy(np.stack([rng.uniform(-0.5, 751.5, 5000), rng.uniform(-0.5, 479.5, 5000)], -1))
    rays = cam.unproject(uv)
    ref = to_ocam(ocam_cam2world(uv.numpy()[:, ::-1], SS, XC, YC, C, D, E))   # to_ocam is its own inverse
    assert cam.pixel_valid(uv).all()
    assert angle_between(rays, torch.from_numpy(ref)).max() < 1e-12


def test_invpol_models_are_world2cam_with_the_axis_on_the_centre():
    # Built from invpol alone, the model is world2cam less invpol(-pi/2), the fit's residual on the axis,
    # which the affine (|A| < 1.001 here) carries to the pixel.
    param = json.loads(JSON.read_text())["front_camera-intrinsic"]["param"]
    K, dist = np.array(param["cam_K"]["data"]), param["cam_dist"]["data"][0]
    cases = [(variant("invpol"), lambda q: ocam_world2cam(to_ocam(q), INVPOL, XC, YC, C, D, E)[:, ::-1], INVPOL),
             (variant("json"), lambda q: avm_world2cam(q, K, dist), dist)]
    for cam, world2cam, invpol in cases:
        b0 = np.polyval(invpol[::-1], -np.pi / 2)
        p = directions(cam.theta_max, 3000, seed=4)[1:]
        uv, _ = cam.project(torch.from_numpy(p))
        assert 1e-4 < abs(b0) < 1e-2
        assert np.abs(uv.numpy() - world2cam(p)).max() <= 1.001 * abs(b0) + 1e-9


def test_json_form_matches_the_txt_form_of_the_same_lens(tmp_path):
    json_from_txt(tmp_path / "front.json")
    K = np.array([[1 / C, E / C, YC], [D / C, 1, XC], [0, 0, 1]])
    p = directions(txt_cam().theta_max, 2000, seed=5)[1:]
    # The two reference world2cams agree on the converted file: the conversion is right.
    via_json = avm_world2cam(p, K, [v * C for v in INVPOL])
    assert np.abs(via_json - ocam_world2cam(to_ocam(p), INVPOL, XC, YC, C, D, E)[:, ::-1]).max() < 1e-9
    from_json = OCamFisheye.from_json(tmp_path / "front.json")
    uv_json, valid_json = from_json.project(torch.from_numpy(p))
    uv_inv, valid_inv = variant("invpol").project(torch.from_numpy(p))
    assert (uv_json - uv_inv).abs().max() < 1e-9 and torch.equal(valid_json, valid_inv)
    # Against the ss model: invpol's fit error, plus the axis residual the invpol model drops.
    uv_ss, _ = txt_cam().project(torch.from_numpy(p))
    fit = np.abs(ocam_world2cam(to_ocam(p), INVPOL, XC, YC, C, D, E)
                 - ocam_world2cam_exact(to_ocam(p), SS, XC, YC, C, D, E)).max()
    b0 = np.polyval(INVPOL[::-1], -np.pi / 2)
    assert (uv_json - uv_ss).abs().max() <= fit + 1.001 * abs(b0) + 1e-9


@pytest.mark.parametrize("which", ["both", "ss", "invpol", "json"])
def test_round_trip_float64(which):
    cam = variant(which)
    rays = torch.from_numpy(directions(cam.theta_max, 20000, seed=6))
    back = cam.unproject(cam.project(rays * 3.7)[0])
    assert angle_between(back, rays).max() < 1e-9
    assert ((back.norm(dim=-1) - 1).abs() < 1e-12).all()


@pytest.mark.parametrize("which", ["both", "invpol", "json"])
def test_round_trip_float32_within_a_few_spacings(which):
    cam = variant(which)
    rays = torch.from_numpy(directions(cam.theta_max, 20000, seed=7))
    uv, _ = cam.project(rays.float())
    back = cam.unproject(uv)
    assert uv.dtype == back.dtype == torch.float32
    # Pixels round at |uv| (one float32 spacing there moves the ray by that over d rho / d theta), rays at 1.
    grid = torch.linspace(0, cam.theta_max, 2001, dtype=torch.float64)
    min_drho = float(cam.drho(grid, cam.k.detach()).min())
    spacing = float(np.spacing(np.float32(uv.abs().max()))) / min_drho + float(np.spacing(np.float32(1.0)))
    assert angle_between(back.double(), rays).max() < 4 * spacing


@pytest.mark.parametrize("which", ["both", "json"])
def test_past_the_valid_angle_is_invalid_on_the_rim_and_never_mirrored(which):
    cam = variant(which)
    az = torch.linspace(0, 2 * math.pi, 13, dtype=torch.float64)[:-1]
    for th in (cam.theta_max + 1e-3, 2.2, 3.0, math.pi - 1e-6):
        p = torch.stack([math.sin(th) * az.cos(), math.sin(th) * az.sin(), math.cos(th) * torch.ones_like(az)], -1)
        uv, valid = cam.project(p * 5.0)
        assert not valid.any() and torch.isfinite(uv).all()
        # On the rim of the valid circle (sensor offsets, before the affine), in the point's own azimuth.
        m = torch.stack(cam._normalised(uv), -1)
        assert torch.allclose(m.norm(dim=-1), torch.full_like(m[:, 0], cam.rho_max), atol=1e-9)
        cos_azimuth = (m * p[:, :2]).sum(-1) / (m.norm(dim=-1) * p[:, :2].norm(dim=-1))
        assert (cos_azimuth > 1 - 1e-12).all()
    # Toward the image corner farthest from the centre the lens is valid up to theta_max and not past it.
    w, h = cam.width - 0.5, cam.height - 0.5
    corners = torch.tensor([[-0.5, -0.5], [w, -0.5], [-0.5, h], [w, h]], dtype=torch.float64)
    far = corners[torch.hypot(*cam._normalised(corners)).argmax()]
    corner = cam.unproject(far[None])
    phi = math.atan2(float(corner[0, 1]), float(corner[0, 0]))
    for th, expect in ((cam.theta_max - 1e-4, True), (cam.theta_max + 1e-4, False)):
        p = torch.tensor([[math.sin(th) * math.cos(phi), math.sin(th) * math.sin(phi), math.cos(th)]],
                         dtype=torch.float64)
        assert cam.project(p)[1].item() is expect
    _, valid = cam.project(torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0]], dtype=torch.float64))
    assert not valid.any()


@pytest.mark.parametrize("which", ["both", "invpol"])
def test_gradients_in_points_pixels_and_polynomial(which):
    cam = variant(which)
    k0 = cam.k.clone()
    # Coefficients span 1e-9..1e2: perturb each relative to itself, k = k0 (1 + w).
    w = torch.zeros_like(k0, requires_grad=True)
    pts = torch.from_numpy(directions(cam.theta_max - 0.05, 6, seed=8)[1:] * 2.0).requires_grad_(True)

    def proj(p, w):
        cam.k = k0 * (1 + w)
        return cam.project(p)[0]

    assert torch.autograd.gradcheck(proj, (pts, w))
    uv = cam.project(pts.detach())[0].detach().requires_grad_(True)

    def unproj(q, w):
        cam.k = k0 * (1 + w)
        return cam.unproject(q)

    assert torch.autograd.gradcheck(unproj, (uv, w))
    cam.k = k0
    # Finite on the axis, at the centre pixel and past the lens.
    edge = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, -1.0]], dtype=torch.float64, requires_grad=True)
    cam.project(edge)[0].sum().backward()
    centre = torch.stack([cam.cx, cam.cy]).detach().reshape(1, 2).requires_grad_(True)
    cam.unproject(centre).sum().backward()
    assert torch.isfinite(edge.grad).all() and torch.isfinite(centre.grad).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_far_and_infinite_points_project_as_their_direction(dtype):
    cam = txt_cam()
    p = torch.tensor([[0.3, -0.2, 1.0], [1.0, 0.5, -0.2], [0.0, 0.0, 1.0]], dtype=dtype)
    uv, valid = cam.project(p)
    big = torch.finfo(dtype).max / 2
    for scale in (1e30, big):
        uv_s, valid_s = cam.project(p * scale)
        assert torch.equal(valid_s, valid) and torch.allclose(uv_s, uv, atol=0, rtol=4 * torch.finfo(dtype).eps)
    # A point at infinity or NaN never gets a wrong pixel marked valid (the shared projection decides which).
    uv_inf, valid_inf = cam.project(torch.tensor([[0.0, 0.0, math.inf], [math.inf, 0.0, 1.0], [math.nan, 0.0, 1.0]],
                                                 dtype=dtype))
    limits = [uv[2], cam.project(p.new_tensor([[1.0, 0.0, 0.0]]))[0][0], None]
    assert all(not bool(v) or torch.equal(got, want) for v, got, want in zip(valid_inf, uv_inf, limits))


def test_serialisation_and_scaling():
    for which in ("both", "invpol", "json"):
        cam = variant(which)
        d = json.loads(json.dumps(cam.to_dict()))
        assert d["model"] == "ocam"
        again = camera_from_dict(d)   # what rig.json and bundles read
        assert isinstance(again, OCamFisheye)
        assert again.to_dict() == cam.to_dict() and again.theta_max == cam.theta_max
        half = cam.scaled(0.5)
        pts = torch.from_numpy(directions(cam.theta_max - 0.01, 200, seed=9))
        assert (half.width, half.height) == (round(cam.width / 2), round(cam.height / 2))
        assert torch.allclose(half.project(pts)[0], (cam.project(pts)[0] + 0.5) * 0.5 - 0.5, atol=1e-9)


def test_bad_input_names_the_file(tmp_path):
    text = TXT.read_text()
    cases = {
        "short.txt": "\n".join(text.splitlines()[:-4]),                       # no image size
        "count.txt": text.replace("5 -2.595395e+02", "6 -2.595395e+02"),      # count != coefficients
        "sign.txt": text.replace("5 -2.595395e+02", "5 2.595395e+02"),        # forward rays with z_o > 0
        "none.txt": "0\n0\n229.5 364.4\n1 0 0\n480 752\n",                     # neither polynomial
        "text.txt": text.replace("229.581672", "centre"),
    }
    for name, text in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(ValueError, match=name):
            OCamFisheye.from_calib_results(tmp_path / name)
    doc = json.loads(JSON.read_text())
    doc["front_camera-intrinsic"]["param"]["cam_K"]["data"][1][1] = 1.2
    (tmp_path / "k11.json").write_text(json.dumps(doc))
    (tmp_path / "junk.json").write_text("{")
    for name in ("k11.json", "junk.json"):
        with pytest.raises(ValueError, match=name):
            OCamFisheye.from_json(tmp_path / name)
