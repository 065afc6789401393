"""A sparse point cloud from a dataset's known poses: features matched between images that see the same part of
the scene, triangulated with every pose held fixed (no bundle adjustment, no pose is estimated).

Rig logs and nerfstudio captures without a PLY come with poses but no points, and 3DGS starts better from points
on the scene's surfaces than from random ones. The steps:

1. SIFT features in every training image (``max_features`` at most, inside the lens' valid circle), as RootSIFT.
2. Image pairs that see the same part of the scene: the same camera at frames up to ``FRAME_WINDOW`` apart, and
   two cameras at the same frame whose optical axes are less than ``NEIGHBOUR_DEG`` apart (a surround-view rig's
   neighbours, not its opposite cameras); matched by nearest descriptor with the ratio test and a mutual check.
3. Every keypoint is a world ray through its own camera model (``CameraModel.unproject``: a fisheye keypoint is a
   fisheye ray, never a pixel of an undistorted pinhole image). A pair's match survives when the midpoint of its
   two rays lies ahead on both and reprojects (``CameraModel.project``) within ``MAX_ERROR_PX`` in both images.
4. Surviving matches join into tracks (connected keypoints; a track holding two keypoints of one image is
   dropped), each triangulated by linear least squares on its rays: the point nearest to all of them. An
   observation that reprojects too far or lies behind its camera is dropped and the track solved again; a point
   is kept when every one of its two or more observations passes and its rays span ``MIN_PARALLAX_DEG``.
5. Each point is coloured by the mean of its keypoints' pixels; ``points3d.ply`` is written atomically.
"""

from __future__ import annotations

import errno
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:   # importers are imported to build `parksim import --help`: no torch at import time
    from ..camera import CameraModel
    from ..data import DatasetReader
    from ..rig import Rig

__all__ = ["SfmError", "SparsePoints", "triangulate_known_poses", "write_sfm_points", "add_to_import", "MAX_FEATURES",
           "MIN_POINTS"]

MAX_FEATURES = 4000
"""Default most SIFT features per image."""
MIN_POINTS = 100
"""Fewest points worth writing: fewer means the images barely match (blank, blurred or not overlapping)."""
FRAME_WINDOW = 3
"""A camera's image is matched with its own images of the next this many frames."""
NEIGHBOUR_DEG = 100.0
"""Two cameras' images of one frame are matched when their optical axes are less than this far apart."""
RATIO = 0.8
"""Lowe's ratio test: the best match's descriptor distance below this fraction of the second best's."""
MAX_ERROR_PX = 2.0
"""Largest reprojection error of an observation kept (pixels)."""
MIN_PARALLAX_DEG = 2.0
"""Smallest angle between a point's rays: below it the depth along the rays is too uncertain."""
CONTRAST = 0.01
"""SIFT's contrast threshold, a quarter of OpenCV's default: dim, low-contrast garages still give features, and
``max_features`` keeps the strongest where there are many."""


class SfmError(ValueError):
    """The images do not give a point cloud (too few features, matches or points); one line saying how far it got."""


@dataclass(frozen=True)
class SparsePoints:
    """A triangulated point cloud and how it was made.

    Attributes:
        xyz: ``[P, 3]`` float64 world positions (m).
        rgb: ``[P, 3]`` uint8 colours.
        track_length: ``[P]`` number of images each point is seen in (at least 2).
        mean_error_px: mean reprojection error over every observation of every point (pixels).
        images: images the features came from.
        pairs: image pairs matched.
        matches: matches that passed the pairwise checks.
    """

    xyz: np.ndarray
    rgb: np.ndarray
    track_length: np.ndarray
    mean_error_px: float
    images: int
    pairs: int
    matches: int

    def report(self) -> dict[str, Any]:
        """The numbers without the arrays, JSON-ready.

        Returns:
            ``points``, ``mean_reprojection_px``, ``mean_track_length``, ``images``, ``pairs``, ``matches``.
        """
        return {"points": len(self.xyz), "mean_reprojection_px": self.mean_error_px,
                "mean_track_length": float(self.track_length.mean()),
                "images": self.images, "pairs": self.pairs, "matches": self.matches}


@dataclass(frozen=True)
class _Features:
    """Every keypoint of every image (view), numbered globally view by view.

    Attributes:
        views: ``(frame, camera)`` of each of the V views.
        poses: ``[V, 4, 4]`` T_world_camera of each view.
        offsets: ``[V + 1]``: view ``v``'s keypoints are ``offsets[v]:offsets[v + 1]``.
        descriptors: V arrays ``[K_v, 128]`` float32, RootSIFT.
        uv: ``[N, 2]`` keypoints (column, row).
        rays: ``[N, 3]`` unit world rays through them.
        colours: ``[N, 3]`` uint8 pixel colours at them.
        view: ``[N]`` the view of each keypoint.
    """

    views: list[tuple[int, str]]
    poses: np.ndarray
    offsets: np.ndarray
    descriptors: list[np.ndarray]
    uv: np.ndarray
    rays: np.ndarray
    colours: np.ndarray
    view: np.ndarray


def _feature_mask(model: CameraModel) -> np.ndarray:
    """uint8 ``[H, W]``: 255 inside the lens' valid circle, shrunk by a few pixels (the rim's edge is no feature)."""
    import cv2

    from ..camera import pixel_grid

    valid = model.pixel_valid(pixel_grid(model.width, model.height)).numpy()
    return cv2.erode(valid.astype(np.uint8) * 255, np.ones((3, 3), np.uint8), iterations=3)


def _features(reader: DatasetReader, views: list[tuple[int, str]], max_features: int, progress: bool) -> _Features:
    """SIFT keypoints of every ``(frame, camera)`` view as RootSIFT, with their world rays and colours."""
    import cv2
    import torch
    from tqdm import tqdm

    sift = cv2.SIFT.create(nfeatures=max_features, contrastThreshold=CONTRAST)
    rig = reader.rig
    masks = {c: _feature_mask(rig.cameras[c].model) for c in rig.names}
    poses = np.stack([reader.camera_pose(c, f).numpy() for f, c in views]).reshape(-1, 4, 4)
    uv, rays, colours, descriptors = [], [], [], []
    for (frame, camera), pose in tqdm(zip(views, poses), total=len(views), desc="sfm features", unit="img",
                                      disable=not progress, file=sys.stderr, dynamic_ncols=True):
        rgb = np.rint(reader.image(camera, frame).numpy() * 255).astype(np.uint8)
        keypoints, desc = sift.detectAndCompute(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), masks[camera])
        pts = np.array([k.pt for k in keypoints], np.float64).reshape(-1, 2)
        desc = np.zeros((0, 128), np.float32) if desc is None else desc.astype(np.float32)
        descriptors.append(np.sqrt(desc / np.maximum(desc.sum(1, keepdims=True), 1e-12)))   # RootSIFT: Hellinger
        uv.append(pts)
        rays.append(rig.cameras[camera].model.unproject(torch.from_numpy(pts)).numpy() @ pose[:3, :3].T)
        px = np.clip(np.rint(pts).astype(int), 0, [rgb.shape[1] - 1, rgb.shape[0] - 1])
        colours.append(rgb[px[:, 1], px[:, 0]])
    counts = [len(p) for p in uv]
    return _Features(views, poses, np.concatenate([[0], np.cumsum(counts)]).astype(int), descriptors,
                     np.concatenate(uv), np.concatenate(rays), np.concatenate(colours),
                     np.repeat(np.arange(len(views)), counts))


def _pairs(feats: _Features, frames: list[int]) -> list[tuple[int, int]]:
    """Indices of the view pairs to match: a camera with itself up to ``FRAME_WINDOW`` frames on, and cameras of
    one frame whose optical axes are within ``NEIGHBOUR_DEG``."""
    order = {f: i for i, f in enumerate(frames)}
    at = {(order[f], c): v for v, (f, c) in enumerate(feats.views)}
    of_frame: dict[int, list[int]] = {}
    for v, (f, _) in enumerate(feats.views):
        of_frame.setdefault(order[f], []).append(v)
    cos_max = math.cos(math.radians(NEIGHBOUR_DEG))
    axes = feats.poses[:, :3, 2]
    pairs = []
    for i, (frame, camera) in enumerate(feats.views):
        k = order[frame]
        pairs += [(i, at[k + gap, camera]) for gap in range(1, FRAME_WINDOW + 1) if (k + gap, camera) in at]
        pairs += [(i, j) for j in of_frame[k] if j > i and axes[i] @ axes[j] > cos_max]
    return sorted(pairs)


def _match(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``[M, 2]`` indices into descriptors ``a`` and ``b`` that are each other's nearest and pass the ratio test."""
    import cv2

    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), int)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    back = np.full(len(b), -1)
    for m in matcher.match(b, a):
        back[m.queryIdx] = m.trainIdx
    found = [(m.queryIdx, m.trainIdx) for m, n in (k for k in matcher.knnMatch(a, b, k=2) if len(k) == 2)
             if m.distance < RATIO * n.distance and back[m.trainIdx] == m.queryIdx]
    return np.array(found, int).reshape(-1, 2)


def _midpoints(c1: np.ndarray, d1: np.ndarray, c2: np.ndarray, d2: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Midpoints ``[M, 3]`` of the closest points of rays ``c1 + s d1`` and ``c2 + t d2`` (unit ``d``), with
    ``s`` and ``t`` ``[M]``; parallel rays get ``s = t = -1`` (not ahead)."""
    w = c1 - c2
    b = (d1 * d2).sum(1)
    d, e = (d1 * w).sum(1), (d2 * w).sum(1)
    denom = 1.0 - b * b
    ok = denom > 1e-12
    safe = np.where(ok, denom, 1.0)
    s = np.where(ok, (b * e - d) / safe, -1.0)
    t = np.where(ok, (e - b * d) / safe, -1.0)
    return 0.5 * (c1 + s[:, None] * d1 + c2 + t[:, None] * d2), s, t


def _reprojection_errors(rig: Rig, feats: _Features, nodes: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Pixel distance ``[O]`` between each keypoint ``nodes`` and its point ``xyz [O, 3]`` projected into the
    keypoint's view; infinite where the point does not project into the image."""
    import torch

    errors = np.full(len(nodes), np.inf)
    view = feats.view[nodes]
    camera_of = np.array([c for _, c in feats.views])[view]
    for camera in np.unique(camera_of):
        pick = camera_of == camera
        poses = feats.poses[view[pick]]
        local = np.einsum("nji,nj->ni", poses[:, :3, :3], xyz[pick] - poses[:, :3, 3])
        projected, valid = rig.cameras[str(camera)].model.project(torch.from_numpy(local))
        err = np.linalg.norm(projected.numpy() - feats.uv[nodes[pick]], axis=1)
        errors[pick] = np.where(valid.numpy(), err, np.inf)
    return errors


def _verified(rig: Rig, feats: _Features, edges: np.ndarray) -> np.ndarray:
    """The matched keypoint pairs ``edges [M, 2]`` (global) whose two rays meet ahead of both cameras, at a point
    that reprojects within ``MAX_ERROR_PX`` in both images."""
    a, b = edges[:, 0], edges[:, 1]
    x, s, t = _midpoints(feats.poses[feats.view[a], :3, 3], feats.rays[a], feats.poses[feats.view[b], :3, 3],
                         feats.rays[b])
    error = _reprojection_errors(rig, feats, edges.T.reshape(-1), np.concatenate([x, x])).reshape(2, -1)
    return edges[(s > 0) & (t > 0) & (error <= MAX_ERROR_PX).all(0)]


def _tracks(feats: _Features, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tracks of matched keypoints: ``(track, node)``, each ``[O]``, the keypoints of tracks with two or more of
    them and none twice from one view; tracks numbered 0..T-1."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(feats.uv)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    nodes = np.unique(edges.reshape(-1))
    track = label[nodes]
    _, first, counts = np.unique(track * len(feats.views) + feats.view[nodes], return_index=True,
                                 return_counts=True)
    twice = track[first[counts > 1]]
    keep = ~np.isin(track, twice)
    _, track = np.unique(track[keep], return_inverse=True)
    return track, nodes[keep]


def _solve(track: np.ndarray, centres: np.ndarray, rays: np.ndarray, count: int) -> np.ndarray:
    """``[T, 3]`` least-squares points: for each track, the point nearest (summed squared distance) to its rays."""
    proj = np.eye(3) - rays[:, :, None] * rays[:, None, :]
    a = np.zeros((count, 3, 3))
    b = np.zeros((count, 3))
    np.add.at(a, track, proj)
    np.add.at(b, track, np.einsum("nij,nj->ni", proj, centres))
    return np.linalg.solve(a, b[:, :, None])[:, :, 0]


def _parallax_ok(track: np.ndarray, rays: np.ndarray, count: int) -> np.ndarray:
    """``[T]``: whether some ray of each track is at least ``MIN_PARALLAX_DEG`` from the track's first ray."""
    first = np.zeros(count, int)
    first[track[::-1]] = np.arange(len(track))[::-1]
    lowest = np.ones(count)
    np.minimum.at(lowest, track, (rays * rays[first[track]]).sum(1))
    return lowest <= math.cos(math.radians(MIN_PARALLAX_DEG))


def _triangulate_tracks(rig: Rig, feats: _Features, track: np.ndarray, nodes: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The points of the tracks that hold up: ``(xyz [P, 3], track [O], node [O], error [O])``, the last three for
    their observations, tracks renumbered 0..P-1. Observations that fail are dropped once and the tracks solved
    again; then a track is kept only if all of its observations pass."""
    count = int(track.max()) + 1 if len(track) else 0
    centres, rays = feats.poses[feats.view[nodes], :3, 3], feats.rays[nodes]
    keep = np.ones(len(nodes), bool)
    xyz, error = np.zeros((count, 3)), np.zeros(len(nodes))
    for final in (False, True):
        good = (np.bincount(track[keep], minlength=count) >= 2) & _parallax_ok(track[keep], rays[keep], count)
        keep &= good[track]
        xyz = np.zeros((count, 3))
        xyz[good] = _solve(np.searchsorted(np.nonzero(good)[0], track[keep]), centres[keep], rays[keep],
                           int(good.sum()))
        error = _reprojection_errors(rig, feats, nodes, xyz[track])
        passed = (((xyz[track] - centres) * rays).sum(1) > 0) & (error <= MAX_ERROR_PX)
        if final:
            whole = np.ones(count, bool)
            np.logical_and.at(whole, track[keep], passed[keep])
            keep &= whole[track]
        else:
            keep &= passed
    kept = np.unique(track[keep])
    return xyz[kept], np.searchsorted(kept, track[keep]), nodes[keep], error[keep]


def triangulate_known_poses(reader: DatasetReader, max_features: int = MAX_FEATURES, progress: bool = True
                            ) -> SparsePoints:
    """Triangulate matched features of a dataset's training images with its poses held fixed.

    Args:
        reader: the dataset (its rig, per-image poses and images; the train split's frames are used, so test views
            stay unseen).
        max_features: most SIFT features per image.
        progress: show progress bars on stderr.

    Returns:
        The points, their colours and how they were made.

    Raises:
        SfmError: no training frames, or fewer than ``MIN_POINTS`` points came out (the message says how many
            features, pairs and matches there were).
        DatasetError: a dataset file is missing or broken.
    """
    from tqdm import tqdm

    train = set(reader.split["train"])
    frames = [f for f in reader.frames if f in train]
    if not frames:
        raise SfmError(f"{reader.layout.split}: no training frames to take points from")
    feats = _features(reader, [(f, c) for f in frames for c in reader.rig.names], max_features, progress)
    pairs = _pairs(feats, frames)
    edges = [np.zeros((0, 2), int)]
    for i, j in tqdm(pairs, desc="sfm matching", unit="pair", disable=not progress, file=sys.stderr,
                     dynamic_ncols=True):
        m = _match(feats.descriptors[i], feats.descriptors[j])
        edges.append(_verified(reader.rig, feats, m + feats.offsets[[i, j]]))
    matches = np.concatenate(edges)
    xyz, track, nodes, error = _triangulate_tracks(reader.rig, feats, *_tracks(feats, matches))
    if len(xyz) < MIN_POINTS:
        raise SfmError(f"{reader.layout.root}: only {len(xyz)} points triangulated, {MIN_POINTS} needed: "
                       f"{len(feats.uv)} features in {len(feats.views)} images, {len(matches)} verified matches in "
                       f"{len(pairs)} image pairs (blank, blurred or barely overlapping images?)")
    length = np.bincount(track, minlength=len(xyz))
    rgb = np.zeros((len(xyz), 3))
    np.add.at(rgb, track, feats.colours[nodes])
    rgb = np.clip(np.rint(rgb / length[:, None]), 0, 255).astype(np.uint8)
    return SparsePoints(xyz, rgb, length, float(error.mean()), len(feats.views), len(pairs), len(matches))


def write_sfm_points(root: str | Path, max_features: int = MAX_FEATURES, overwrite: bool = False,
                     progress: bool = True) -> SparsePoints:
    """Triangulate a dataset's points from its known poses and write them as its ``points3d.ply``, atomically.

    Args:
        root: the dataset directory.
        max_features: most SIFT features per image.
        overwrite: replace an existing ``points3d.ply`` (checked before any work).
        progress: show progress bars on stderr.

    Returns:
        The points written and how they were made.

    Raises:
        FileExistsError: ``points3d.ply`` exists and ``overwrite`` is off.
        SfmError: too few points came out; nothing is written.
        DatasetError: a dataset file is missing or broken.
    """
    from ..data import DatasetReader, DatasetWriter
    from ..fileio import atomic_files

    reader = DatasetReader(root)
    target = reader.layout.points
    if target.exists() and not overwrite:
        raise FileExistsError(errno.EEXIST, "already exists; pass --overwrite to replace it", str(target))
    points = triangulate_known_poses(reader, max_features, progress)
    xyz = points.xyz.astype(np.float32)
    atomic_files(reader.layout.root, lambda tmp: DatasetWriter(tmp).points(xyz, points.rgb, np.zeros_like(xyz)))
    return points


def add_to_import(root: Path, progress: bool = True) -> dict[str, Any]:
    """``import --points sfm``: write a just-imported dataset's points from its poses (replacing the recording's own)
    and record them in its ``import_report.json``.

    Args:
        root: the dataset an import has just written.
        progress: show progress bars on stderr.

    Returns:
        The report's new entries: ``points`` (the count) and ``points_sfm`` (``SparsePoints.report()``).

    Raises:
        SfmError: too few points came out; the dataset stays as imported, its report unchanged.
    """
    from ..fileio import write_json
    from .recording import REPORT_FILE

    try:
        points = write_sfm_points(root, overwrite=True, progress=progress)
    except SfmError as e:
        raise SfmError(f"--points sfm: {e}; {root} is imported without SfM points") from None
    added = {"points": len(points.xyz), "points_sfm": points.report()}
    report = json.loads((root / REPORT_FILE).read_text())
    write_json(root / REPORT_FILE, {**report, **added})
    return added
