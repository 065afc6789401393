"""GCN-Parking-style detector: point head + descriptors sampled at the points, an attentional graph, edge scores."""

from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .backbone import PointMaps, _conv
from .base import Detector
from .decode import DecodeOptions, MarkingPoint, Slot, decode_points, select_slots

__all__ = ["GCNDetector", "NODE_FEATURES"]

NODE_FEATURES = 5
"""Per-node input of the positional encoder: u, v in [0, 1], cos and sin of the direction, 1 if L-shaped."""


def _mlp(cin: int, hidden: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(cin, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, cout))


class GCNDetector(Detector):
    """The shared point detector plus GCN-Parking's descriptor, graph and edge classifier over ordered point pairs."""

    kind = "gcn"

    def __init__(self, width: float = 0.25, input_size: int = 256, descriptor_dim: int = 64,
                 graph_layers: int = 3, heads: int = 4) -> None:
        super().__init__(width, input_size)
        self.descriptor_dim, self.graph_layers, self.heads = descriptor_dim, graph_layers, heads
        c8 = self.backbone.channels[2]
        self.descriptor_head = nn.Sequential(_conv(c8, c8, 3), nn.Conv2d(c8, descriptor_dim, 1))
        self.pos_encoder = _mlp(NODE_FEATURES, descriptor_dim, descriptor_dim)
        self.graph = nn.ModuleList(
            nn.TransformerEncoderLayer(descriptor_dim, heads, 2 * descriptor_dim, dropout=0.0, batch_first=True,
                                       norm_first=True) for _ in range(graph_layers))
        self.edge_head = _mlp(2 * descriptor_dim, descriptor_dim, 1)

    def run(self, bev: Tensor) -> tuple[PointMaps, Tensor]:
        """Point maps and the stride-8 descriptor map ``[B, D, S/8, S/8]``."""
        feats = self.features(bev)
        return self.point_head(feats[-1]), self.descriptor_head(feats[0])

    def edge_logits(self, descriptors: Tensor, nodes: Tensor, mask: Tensor) -> Tensor:
        """Ordered-pair slot logits ``[B, N, N]`` for nodes ``[B, N, 5]`` (padding where ``mask`` is False)."""
        grid = nodes[:, None, :, :2] * 2 - 1
        desc = F.grid_sample(descriptors, grid, mode="bilinear", align_corners=False)[:, :, 0].transpose(1, 2)
        x = F.normalize(desc, dim=-1) + self.pos_encoder(nodes)
        attend = mask.clone()
        attend[~mask.any(dim=1), 0] = True  # a graph without nodes keeps one key: no all-masked softmax (NaN)
        for layer in self.graph:
            x = layer(x, src_key_padding_mask=~attend)
        n = x.shape[1]
        pairs = torch.cat([x[:, :, None].expand(-1, -1, n, -1), x[:, None].expand(-1, n, -1, -1)], dim=-1)
        return self.edge_head(pairs)[..., 0]

    @staticmethod
    def nodes_of(points: list[MarkingPoint], size: tuple[int, int]) -> Tensor:
        """Node features ``[1, N, 5]`` of detected points in a ``size`` = (W, H) BEV."""
        w, h = size
        rows = [[(p.x + 0.5) / w, (p.y + 0.5) / h, math.cos(p.direction), math.sin(p.direction),
                 float(p.shape == "L")] for p in points]
        return torch.tensor(rows, dtype=torch.float32).reshape(1, -1, NODE_FEATURES)

    def slots_of(self, points: list[MarkingPoint], b: int, extras: Any, size: tuple[int, int], m_per_px: float,
                 opts: DecodeOptions) -> list[Slot]:
        """Slots from the edge scores: ordered pairs above ``edge_threshold``, scored by edge x weaker point."""
        if len(points) < 2:
            return []
        nodes = self.nodes_of(points, size).to(extras.device)
        everyone = torch.ones(1, len(points), dtype=torch.bool, device=extras.device)
        scores = torch.sigmoid(self.edge_logits(extras[b:b + 1], nodes, everyone))[0]
        candidates = [(float(scores[i, j]) * min(points[i].score, points[j].score), i, j)
                      for i, j in (scores > opts.edge_threshold).nonzero().tolist() if i != j]
        return select_slots(points, candidates)

    def edges(self, bev: Tensor, opts: DecodeOptions = DecodeOptions()) -> list[tuple[Tensor, Tensor]]:
        """Per image: detected point locations ``[N, 2]`` (BEV px, constants) and the edge-score matrix ``[N, N]``
        in [0, 1], differentiable w.r.t. ``bev`` (what the slot edge-aware loss rasterizes)."""
        height, width = bev.shape[-2:]
        maps, descriptors = self.run(bev)
        out = []
        for b in range(maps.logits.shape[0]):
            points = decode_points(maps, b, width, height, opts)
            locations = torch.tensor([[p.x, p.y] for p in points], dtype=bev.dtype).reshape(-1, 2)
            if not points:
                out.append((locations, bev.new_zeros(0, 0)))
                continue
            nodes = self.nodes_of(points, (width, height)).to(bev)
            logits = self.edge_logits(descriptors[b:b + 1], nodes,
                                      torch.ones(1, len(points), dtype=torch.bool, device=bev.device))
            out.append((locations, torch.sigmoid(logits[0])))
        return out

    def config(self) -> dict[str, Any]:
        """Constructor arguments (stored in checkpoints)."""
        return {**super().config(), "descriptor_dim": self.descriptor_dim, "graph_layers": self.graph_layers,
                "heads": self.heads}
