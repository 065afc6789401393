"""A dataset seen at a lower resolution: the training image scale (``data.image_scale``).

``ScaledReader`` is a ``DatasetReader`` whose rig has every camera scaled by ``s`` (``CameraModel.scaled``: sizes
rounded to whole pixels, the pixel-centre convention) and whose images and depth maps are resized to those sizes.
The trainer and ``parksim eval`` take it in place of the dataset's reader, so renders, masks, the camera response's
radius maps, pose alignment and the slot-aware IPM all see one consistent, smaller set of cameras; the bundle keeps
the full-size rig (``full_size_rig``), so a scene trained at 0.5 still serves at any scale.
"""

from __future__ import annotations

from functools import cached_property

import cv2
import torch
from torch import Tensor

from parksim.data import DatasetReader
from parksim.rig import Rig, RigCamera

__all__ = ["ScaledReader", "at_scale", "scaled_rig", "full_size_rig"]


def scaled_rig(rig: Rig, scale: float) -> Rig:
    """``rig`` with every camera imaged at ``scale`` times its resolution (extrinsics and BEV unchanged).

    Args:
        rig: the full-size rig.
        scale: the resolution factor, in (0, 1].

    Returns:
        A new rig (``rig`` itself at scale 1).
    """
    if scale == 1.0:
        return rig
    return Rig({c: RigCamera(c, cam.model.scaled(scale), cam.T_vehicle_camera) for c, cam in rig.cameras.items()},
               rig.bev)


def full_size_rig(rig: Rig, full: Rig) -> Rig:
    """``rig``'s extrinsics (a refined, scaled rig's) with ``full``'s intrinsics: the rig a bundle keeps.

    Args:
        rig: the rig trained with (its cameras possibly scaled).
        full: the dataset's full-size rig (same camera names).

    Returns:
        A rig with ``full``'s camera models and BEV and ``rig``'s ``T_vehicle_camera`` (``rig`` itself when its
        cameras already have ``full``'s models: training at scale 1).
    """
    if all(cam.model is full.cameras[c].model for c, cam in rig.cameras.items()):
        return rig
    return Rig({c: RigCamera(c, full.cameras[c].model, cam.T_vehicle_camera) for c, cam in rig.cameras.items()},
               full.bev)


class ScaledReader(DatasetReader):
    """The dataset ``reader`` reads, its cameras scaled by ``scale``: ``rig``, ``image`` and ``depth`` differ.

    Images are decoded and checked at full size by ``reader``, then resized with ``cv2.INTER_AREA`` (the average
    of the pixels each output pixel covers); depth maps with ``cv2.INTER_NEAREST`` (an average of depths across an
    edge is no surface's depth). Poses, split, map and labels are the dataset's.
    """

    def __init__(self, reader: DatasetReader, scale: float) -> None:
        """Wrap ``reader``.

        Args:
            reader: the dataset at full size (already validated).
            scale: the resolution factor, in (0, 1).
        """
        super().__init__(reader.layout.root, validate=False)
        self.full, self.scale = reader, scale

    @cached_property
    def rig(self) -> Rig:
        """The dataset's rig with every camera scaled (``scaled_rig``)."""
        return scaled_rig(self.full.rig, self.scale)

    def _size(self, camera: str) -> tuple[int, int]:
        """``(width, height)`` of ``camera`` at this scale."""
        model = self.rig.cameras[camera].model
        return model.width, model.height

    def image(self, camera: str, frame: int) -> Tensor:
        """The full-size image (checked as ``DatasetReader.image`` checks it) resized to the scaled camera.

        Args:
            camera: the camera's name in the rig.
            frame: the frame id.

        Returns:
            ``[h, w, 3]`` float32 in [0, 1] at the scaled camera's size.
        """
        full = self.full.image(camera, frame).numpy()
        return torch.from_numpy(cv2.resize(full, self._size(camera), interpolation=cv2.INTER_AREA))

    def depth(self, camera: str, frame: int) -> Tensor:
        """The full-size depth map resized (nearest pixel) to the scaled camera.

        Args:
            camera: the camera's name in the rig.
            frame: the frame id.

        Returns:
            ``[h, w]`` float32 metres (0 = no depth).
        """
        full = self.full.depth(camera, frame).numpy()
        return torch.from_numpy(cv2.resize(full, self._size(camera), interpolation=cv2.INTER_NEAREST))


def at_scale(reader: DatasetReader, scale: float) -> DatasetReader:
    """``reader`` seen at ``scale``: itself at 1 (bit for bit the full-size path), else a ``ScaledReader``.

    Args:
        reader: the dataset at full size.
        scale: the resolution factor, in (0, 1].

    Returns:
        The reader to train or score with.
    """
    return reader if scale == 1.0 else ScaledReader(reader, scale)
