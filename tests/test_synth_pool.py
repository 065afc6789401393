"""``write_frames`` with a process pool writes exactly the files a serial run writes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from parksim.cli import main
from parksim.data import DatasetReader, DatasetWriter
from parksim.data.writer import to_uint8
from parksim.synth import SceneRenderer, get_preset
from parksim.synth.generate import write_frames


def _files(root):
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_pool_output_is_byte_identical_to_serial(tmp_path, tiny_data):
    """Two pool workers against the session's tiny dataset (a job that small runs serially by default)."""
    pool = tmp_path / "pool"
    assert main(["synth", "tiny", "-o", str(pool), "--workers", "2", "--quiet"]) == 0
    pooled, ref = _files(pool), _files(tiny_data)
    assert sorted(pooled) == sorted(ref)
    assert len([k for k in ref if k.startswith("images/")]) == 4 * get_preset("tiny").frames
    different = [k for k in ref if pooled[k] != ref[k]]
    assert not different, different


def test_frame_ids_and_exposure_frames(tmp_path, tiny_data):
    """Files are named by the frame ids given (which seed the noise); each view's exposure drift is its exposure
    frame's, so a view written as frame 1004 with exposure frame 4 is the render of frame 1004 at frame 4's
    exposure."""
    tiny = get_preset("tiny")
    pose = DatasetReader(tiny_data).pose(4).numpy()
    writer = DatasetWriter(tmp_path)
    write_frames(tiny, writer, pose[None], [4], workers=1)
    assert (tmp_path / "images/front/000004.png").read_bytes() == (tiny_data / "images/front/000004.png").read_bytes()
    write_frames(tiny, writer, pose[None], [1004], workers=1, exposure_frames=[4])
    written = cv2.cvtColor(cv2.imread(str(tmp_path / "images/front/001004.png")), cv2.COLOR_BGR2RGB)
    renderer = SceneRenderer(tiny)
    shared = to_uint8(renderer.render(pose, 1004, ["front"], exposure_frame=4)["front"].image)
    own = to_uint8(renderer.render(pose, 1004, ["front"])["front"].image)
    assert np.array_equal(written, shared)
    assert not np.array_equal(written, own)


def test_bad_arguments(tmp_path):
    writer = DatasetWriter(tmp_path)
    with pytest.raises(ValueError, match="2 frame ids"):
        write_frames(get_preset("tiny"), writer, np.eye(4)[None], [0, 1], workers=1)
    with pytest.raises(ValueError, match="workers"):
        write_frames(get_preset("tiny"), writer, np.eye(4)[None], [0], workers=0)
