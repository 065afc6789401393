"""BEV images with slot labels from ParkSim dataset folders or ps2.0-style folders, and training augmentation."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from .labels_ps2 import SlotLabels, read_ps2_labels
from .targets import graph_targets, point_targets

__all__ = ["BEVItem", "iter_items", "rotate", "hflip", "photometric", "TrainingSet", "SPLITS"]

SPLITS = ("train", "test", "all")


@dataclass
class BEVItem:
    """One BEV image (uint8 RGB ``[H, W, 3]``) with its labels; ``name`` says where it came from."""

    name: str
    image: np.ndarray
    labels: SlotLabels


def _is_parksim(folder: Path) -> bool:
    return (folder / "rig.json").is_file()


def _parksim_items(folder: Path, split: str) -> Iterator[BEVItem]:
    from parksim.data import DatasetReader

    reader = DatasetReader(folder, validate=False)
    if not (reader.has_ipm and reader.has_labels):
        raise FileNotFoundError(f"{folder}: needs ipm/ (ground-truth BEVs) and labels/ to train or evaluate detectors")
    bev = reader.rig.bev
    frames = reader.frames if split == "all" else reader.split[split]
    for f in frames:
        image = (reader.ipm(f).numpy() * 255.0 + 0.5).astype(np.uint8)
        labels = SlotLabels.from_parksim(reader.labels(f), bev.width, bev.height, bev.m_per_px,
                                         reader.layout.labels(f))
        yield BEVItem(f"{folder.name}/{f}", image, labels)


def _ps2_items(folder: Path) -> Iterator[BEVItem]:
    files = sorted([*folder.glob("*.json"), *folder.glob("*.mat")])
    if not files:
        raise FileNotFoundError(f"{folder}: neither a ParkSim dataset (rig.json) nor a ps2.0 folder (*.json or *.mat "
                                "labels)")
    for path in files:
        image_path = next((path.with_suffix(s) for s in (".jpg", ".png") if path.with_suffix(s).is_file()), None)
        if image_path is None:
            raise FileNotFoundError(f"{path}: no image {path.stem}.jpg or .png next to the label file")
        image = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
        if image is None:
            raise ValueError(f"{image_path}: cannot decode the image")
        h, w = image.shape[:2]
        yield BEVItem(f"{folder.name}/{path.stem}", cv2.cvtColor(image, cv2.COLOR_BGR2RGB), read_ps2_labels(path, w, h))


def iter_items(folder: str | Path, split: str = "train") -> Iterator[BEVItem]:
    """BEVs of a ParkSim dataset (frames of ``split``) or of a ps2.0 folder (all of its images)."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: data folder not found")
    return _parksim_items(folder, split) if _is_parksim(folder) else _ps2_items(folder)


def resize(item: BEVItem, size: int) -> BEVItem:
    """The item at ``size`` x ``size`` px, labels scaled with it (pixel centres stay at integers)."""
    h, w = item.image.shape[:2]
    sx, sy = size / w, size / h
    marks = item.labels.marks.copy()
    marks[:, 0] = (marks[:, 0] + 0.5) * sx - 0.5
    marks[:, 1] = (marks[:, 1] + 0.5) * sy - 0.5
    marks[:, 2] = np.arctan2(np.sin(marks[:, 2]) * sy, np.cos(marks[:, 2]) * sx)
    image = cv2.resize(item.image, (size, size), interpolation=cv2.INTER_AREA)
    labels = replace(item.labels, marks=marks, width=size, height=size, m_per_px=item.labels.m_per_px / sx)
    return BEVItem(item.name, image, labels)


def _keep(labels: SlotLabels, marks: np.ndarray) -> SlotLabels:
    """Labels with the transformed ``marks``, dropping points that left the image and the slots that used them."""
    inside = ((marks[:, 0] >= -0.5) & (marks[:, 0] <= labels.width - 0.5)
              & (marks[:, 1] >= -0.5) & (marks[:, 1] <= labels.height - 0.5))
    new_index = np.cumsum(inside) - 1
    keep_slot = inside[labels.slots[:, 0]] & inside[labels.slots[:, 1]] if len(labels.slots) else np.zeros(0, bool)
    return replace(labels, marks=marks[inside], slots=new_index[labels.slots[keep_slot]].reshape(-1, 2),
                   slot_angles=labels.slot_angles[keep_slot])


def rotate(image: np.ndarray, labels: SlotLabels, degrees: float) -> tuple[np.ndarray, SlotLabels]:
    """Rotate the BEV about its centre (counter-clockwise as viewed); points leaving the image are dropped."""
    h, w = image.shape[:2]
    m = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), degrees, 1.0)
    out = cv2.warpAffine(image, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    marks = labels.marks.copy()
    marks[:, :2] = labels.marks[:, :2] @ m[:, :2].T + m[:, 2]
    dirs = np.stack([np.cos(marks[:, 2]), np.sin(marks[:, 2])], 1) @ m[:, :2].T
    marks[:, 2] = np.arctan2(dirs[:, 1], dirs[:, 0])
    return out, _keep(labels, marks)


def hflip(image: np.ndarray, labels: SlotLabels) -> tuple[np.ndarray, SlotLabels]:
    """Mirror left-right: the slot side flips, so each slot's points swap and its angle becomes 180 - angle."""
    marks = labels.marks.copy()
    marks[:, 0] = labels.width - 1 - marks[:, 0]
    marks[:, 2] = np.arctan2(np.sin(marks[:, 2]), -np.cos(marks[:, 2]))
    flipped = replace(labels, marks=marks, slots=labels.slots[:, ::-1].copy(), slot_angles=180.0 - labels.slot_angles)
    return np.ascontiguousarray(image[:, ::-1]), flipped


def photometric(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Random gamma, contrast, brightness, per-channel gain and sensor noise on a uint8 RGB image -> float32 in [0, 1].

    The colour change is one 256-entry table per channel (``cv2.LUT``) and the noise comes from OpenCV's generator
    (seeded from ``rng``): several times cheaper than float tensor arithmetic, which dominated a training step.
    """
    gamma, contrast, brightness = rng.uniform(0.7, 1.4), rng.uniform(0.6, 1.4), rng.uniform(0.6, 1.4)
    gain, sigma = rng.uniform(0.85, 1.15, 3), rng.uniform(0.0, 0.04)
    levels = np.maximum(np.arange(256) / 255.0, 1e-4) ** gamma
    mean = np.bincount(image.ravel(), minlength=256) @ levels / image.size
    table = (((levels - mean) * contrast + mean * brightness)[:, None] * gain).astype(np.float32)
    out = cv2.LUT(np.ascontiguousarray(image), table.reshape(256, 1, 3))
    noise = np.empty_like(out)
    cv2.setRNGSeed(int(rng.integers(2**31)))
    cv2.randn(noise, 0.0, float(sigma))  # type: ignore[call-overload]  # the stubs miss OpenCV's scalar mean/stddev
    return np.clip(out + noise, 0.0, 1.0)


class TrainingSet:
    """Training BEVs resized once to the network input; ``batch`` draws augmented images and targets."""

    def __init__(self, folders: list[str | Path], size: int, max_nodes: int = 32) -> None:
        self.size, self.max_nodes = size, max_nodes
        self.items = [resize(item, size) for folder in folders for item in iter_items(folder, "train")]
        if not self.items:
            raise ValueError(f"no training BEVs in {[str(f) for f in folders]}")
        plain = next((item.name for item in self.items if not item.labels.directional), None)
        if plain is not None:
            raise ValueError(f"{plain}: labels without marking-point directions and shapes (ps2.0's original form) "
                             "can score slots but cannot train a detector; use DMPR-PS's directional labels")

    def __len__(self) -> int:
        return len(self.items)

    def sample(self, index: int, rng: np.random.Generator, augment: bool) -> tuple[np.ndarray, SlotLabels]:
        """Item ``index``, randomly rotated (any angle, 80 % of the time) and mirrored (half the time)."""
        item = self.items[index]
        image, labels = item.image, item.labels
        if augment and rng.random() < 0.8:
            image, labels = rotate(image, labels, float(rng.uniform(0.0, 360.0)))
        if augment and rng.random() < 0.5:
            image, labels = hflip(image, labels)
        return image, labels

    def batch(self, batch_size: int, rng: np.random.Generator, grid: int, augment: bool = True) -> dict[str, Tensor]:
        """Images ``[B, 3, S, S]``, point targets ``[B, 6, G, G]``, graph nodes/mask/edges (GCN)."""
        images, points, nodes, masks, edges = [], [], [], [], []
        for index in rng.integers(0, len(self.items), batch_size):
            image, labels = self.sample(int(index), rng, augment)
            pixels = photometric(image, rng) if augment else image.astype(np.float32) / 255.0
            images.append(torch.from_numpy(pixels).permute(2, 0, 1))
            points.append(point_targets(labels.marks, self.size, grid))
            n, m, e = graph_targets(labels.marks, labels.slots, self.size, self.max_nodes, 1.0, rng)
            nodes.append(n)
            masks.append(m)
            edges.append(e)
        return {"images": torch.stack(images), "points": torch.stack(points), "nodes": torch.stack(nodes),
                "mask": torch.stack(masks), "edges": torch.stack(edges)}

