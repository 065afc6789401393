"""Detector training on ground-truth BEVs: DMPR-PS point loss, plus GCN-Parking's edge loss; checkpoints + progress."""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..losses import sum_terms
from .backbone import PointMaps
from .base import Detector
from .dataset import TrainingSet
from .gcn import GCNDetector
from .registry import DETECTORS

__all__ = ["TrainOptions", "train_detector", "point_loss", "edge_loss", "init_from"]


@dataclass(frozen=True)
class TrainOptions:
    """Model size and schedule; the defaults train on this 2-core CPU in minutes."""

    arch: str = "dmpr"
    width: float = 0.25
    input_size: int = 256
    steps: int = 1200
    batch_size: int = 8
    lr: float = 2e-3
    weight_decay: float = 1e-4
    seed: int = 0
    threads: int = 2
    checkpoint_every: int = 250
    init: str | None = None      # start from this checkpoint's matching weights (e.g. GCN from a DMPR model)
    device: str = "cpu"          # "cuda" trains on the GPU (data are batched on the CPU and copied over)

    def __post_init__(self) -> None:
        if self.arch not in DETECTORS:
            raise ValueError(f"arch must be {' or '.join(map(repr, DETECTORS))}, got {self.arch!r}")
        for name in ("steps", "batch_size", "threads", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.device.split(":")[0] not in ("cpu", "cuda"):
            raise ValueError(f"device must be 'cpu' or 'cuda[:N]', got {self.device!r}")
        if not self.lr > 0:
            raise ValueError(f"lr must be positive, got {self.lr}")


def point_loss(maps: PointMaps, target: Tensor) -> Tensor:
    """DMPR-PS loss: confidence on every cell; shape, offset and direction only where a point is labelled."""
    logits = maps.logits
    pos = target[:, 0:1]
    conf = F.binary_cross_entropy_with_logits(logits[:, 0:1], pos, pos_weight=logits.new_tensor(4.0))
    n = pos.sum().clamp(min=1.0)
    shape = (F.binary_cross_entropy_with_logits(logits[:, 1:2], target[:, 1:2], reduction="none") * pos).sum() / n
    offset = (((maps.offset - target[:, 2:4]) ** 2) * pos).sum() / n
    direction = (((torch.tanh(logits[:, 4:6]) - target[:, 4:6]) ** 2) * pos).sum() / n
    return conf + 0.5 * shape + 10.0 * offset + direction


def edge_loss(logits: Tensor, edges: Tensor, mask: Tensor) -> Tensor:
    """Binary cross-entropy over the ordered pairs of real, distinct nodes (slots are rare: positives weighted)."""
    valid = mask[:, :, None] & mask[:, None, :] & ~torch.eye(mask.shape[1], dtype=torch.bool, device=mask.device)[None]
    loss = F.binary_cross_entropy_with_logits(logits, edges, reduction="none", pos_weight=logits.new_tensor(3.0))
    return (loss * valid).sum() / valid.sum().clamp(min=1)


def build(opts: TrainOptions) -> Detector:
    """A fresh model of ``opts.arch``."""
    return DETECTORS[opts.arch](width=opts.width, input_size=opts.input_size)


def init_from(model: nn.Module, path: str | Path) -> int:
    """Copy the weights of the checkpoint at ``path`` whose names and shapes match ``model``; returns how many."""
    source = Path(path)
    source = source / "model.pt" if source.is_dir() else source
    if not source.is_file():
        raise FileNotFoundError(f"{source}: checkpoint to initialise from not found")
    state = torch.load(source, map_location="cpu", weights_only=True)["state_dict"]
    own = model.state_dict()
    shared = {k: v for k, v in state.items() if k in own and own[k].shape == v.shape}
    if not shared:
        raise ValueError(f"{source}: no weights match this model (different width or architecture?)")
    model.load_state_dict(shared, strict=False)
    return len(shared)


def _init_seconds(init: str | None) -> float:
    """Training time already spent on the model ``init`` points to (0 without one or without its train.json)."""
    if not init:
        return 0.0
    folder = Path(init) if Path(init).is_dir() else Path(init).parent
    meta = folder / "train.json"
    return float(json.loads(meta.read_text()).get("total_train_seconds", 0.0)) if meta.is_file() else 0.0


def train_detector(folders: list[str | Path], out: str | Path, opts: TrainOptions = TrainOptions(),
                   progress: bool = True) -> Path:
    """Train on the train frames of ``folders``; writes ``model.pt`` and ``train.json`` into ``out``."""
    from tqdm import tqdm

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(opts.threads)
    torch.manual_seed(opts.seed)
    rng = np.random.default_rng(opts.seed)
    model = build(opts)
    if opts.init:
        init_from(model, opts.init)
    model.to(opts.device)
    data = TrainingSet(folders, opts.input_size)
    grid = opts.input_size // 32
    optim = torch.optim.AdamW(model.parameters(), lr=opts.lr, weight_decay=opts.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(optim, max_lr=opts.lr, total_steps=opts.steps, pct_start=0.1)
    meta = {"options": asdict(opts), "folders": [str(f) for f in folders], "images": len(data)}
    before = _init_seconds(opts.init)
    start = time.perf_counter()
    model.train()
    bar = tqdm(range(1, opts.steps + 1), desc=f"train {opts.arch}", unit="step", disable=not progress)
    for step in bar:
        batch = {k: v.to(opts.device) for k, v in data.batch(opts.batch_size, rng, grid).items()}
        maps, extras = model.run(batch["images"])
        losses = {"points": point_loss(maps, batch["points"])}
        if isinstance(model, GCNDetector):
            losses["edges"] = edge_loss(model.edge_logits(extras, batch["nodes"], batch["mask"]), batch["edges"],
                                        batch["mask"])
        loss = sum_terms(losses.values())
        optim.zero_grad(set_to_none=True)
        loss.backward()
        optim.step()
        sched.step()
        bar.set_postfix({k: f"{v.item():.3f}" for k, v in losses.items()})
        if step % opts.checkpoint_every == 0 or step == opts.steps:
            seconds = time.perf_counter() - start
            meta.update(step=step, train_seconds=seconds, total_train_seconds=before + seconds)
            model.eval().save(out / "model.pt", {"meta": meta})
            model.train()
    (out / "train.json").write_text(json.dumps(meta, indent=1))
    return out / "model.pt"
