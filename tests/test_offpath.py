"""Off-path test split: exact offsets, colliding poses skipped, the written split equals direct renders, the CLI's
bad inputs, and `parksim eval` / the paper tables scoring it on a tiny trained bundle."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from parksim.cli import main
from parksim.data import DatasetReader
from parksim.data.writer import to_uint8
from parksim.recon.config import dump_config, load_config
from parksim.recon.detectors import DecodeOptions, load_detector
from parksim.recon.detectors.train import TrainOptions, train_detector
from parksim.recon.paper_eval import evaluate_runs
from parksim.recon.reconstruct import reconstruct
from parksim.synth import get_preset
from parksim.synth.generate import SceneRenderer, scene_map
from parksim.synth.layout import build_garage
from parksim.synth.offpath import (
    CLEARANCE,
    FRAME_BASE,
    LATERAL_M,
    MANOEUVRE_STEPS,
    YAW_DEG,
    group_frames,
    offpath_poses,
    read_offpath,
)
from parksim.synth.trajectory import drive
from parksim.vehicle import Obstacles, VehicleParams, footprint

EPS = np.finfo(np.float64).eps


def _yaw(pose: np.ndarray) -> float:
    return math.atan2(pose[1, 0], pose[0, 0])


@pytest.fixture(scope="module")
def recorded() -> dict:
    """The tiny preset's recorded poses and map, without rendering anything."""
    preset = get_preset("tiny")
    garage = build_garage(preset.layout)
    poses, _ = drive(garage, preset.trajectory, preset.frames)
    frames = list(range(preset.frames))
    return {"poses": poses, "frames": frames, "test": [f for f in frames if f % 10 == 0],
            "map": json.loads(json.dumps(scene_map(garage)))}


def test_lateral_offsets_are_perpendicular_and_yaw_offsets_exact(recorded: dict) -> None:
    r = recorded
    split = offpath_poses(r["poses"], r["frames"], r["test"], r["map"])
    assert [d["frame"] for d in split.descriptors] == list(range(FRAME_BASE, FRAME_BASE + len(split.poses)))
    seen = {(d["base"], d["kind"], d["offset"]) for d in split.descriptors}
    for pose, d in zip(split.poses, split.descriptors):
        base = r["poses"][d["base"]]
        if d["kind"] == "lateral":
            step = pose[:3, 3] - base[:3, 3]
            heading = base[:3, 0]
            scale = np.abs(base[:3, 3]).max()
            assert abs(step @ heading) <= 4 * EPS * scale          # perpendicular to the heading
            assert np.linalg.norm(step) == pytest.approx(abs(d["offset"]), abs=4 * EPS * scale)
            assert (heading[0] * step[1] - heading[1] * step[0]) * d["offset"] > 0   # positive offsets go left
            np.testing.assert_array_equal(pose[:3, :3], base[:3, :3])   # heading unchanged
        elif d["kind"] == "yaw":
            np.testing.assert_array_equal(pose[:3, 3], base[:3, 3])     # turned about the ego origin
            turn = math.remainder(_yaw(pose) - _yaw(base), 2 * math.pi)
            assert turn == pytest.approx(math.radians(d["offset"]), abs=8 * EPS)
    wanted = {(f, "lateral", s * v) for f in r["test"] for v in LATERAL_M for s in (1, -1)}
    wanted |= {(f, "yaw", s * v) for f in r["test"] for v in YAW_DEG for s in (1, -1)}
    skipped = sum(v for k, v in split.skipped.items() if not k.startswith("slot_"))
    lateral_yaw = {k for k in seen if k[1] != "manoeuvre"}
    assert lateral_yaw <= wanted and len(wanted - lateral_yaw) <= skipped


def test_manoeuvres_end_in_the_slot(recorded: dict) -> None:
    r = recorded
    split = offpath_poses(r["poses"], r["frames"], r["test"], r["map"])
    ends = [(p, d) for p, d in zip(split.poses, split.descriptors) if d["kind"] == "manoeuvre"]
    assert ends, "the tiny garage has a free slot beside its path"
    p, d = ends[-1]
    slot = r["map"]["slots"][d["slot"]]
    corners = np.asarray(slot["corners"])
    into = corners[3] - corners[0]
    x0, x1, _, _ = VehicleParams().extent
    centre = p[:2, 3] + p[:2, 0] * (x0 + x1) / 2
    np.testing.assert_allclose(centre, corners.mean(0), atol=1e-9)     # body centred in the slot
    assert math.remainder(_yaw(p) - math.atan2(into[1], into[0]), 2 * math.pi) == pytest.approx(0, abs=1e-9)
    assert not slot["occupied"] and d["offset"] > 0
    assert len([x for x in split.descriptors if x.get("slot") == d["slot"]]) <= MANOEUVRE_STEPS


def test_poses_on_obstacles_are_skipped_and_counted(recorded: dict) -> None:
    r = recorded
    base = r["poses"][0]
    left = base[:2, 3] + base[:2, 1] * 1.6 + base[:2, 0] * 1.4        # 1.6 m left of frame 0's body centre
    pillar = {"kind": "pillar", "center": left.tolist(), "size": [0.4, 0.4], "z": [0.0, 2.9], "yaw": 0.0}
    with_pillar = {**r["map"], "obstacles": [*r["map"]["obstacles"], pillar], "slots": []}
    plain = offpath_poses(r["poses"], r["frames"], [0], {**r["map"], "slots": []})
    blocked = offpath_poses(r["poses"], r["frames"], [0], with_pillar)
    gone = {(d["kind"], d["offset"]) for d in plain.descriptors} - {(d["kind"], d["offset"]) for d in
                                                                      blocked.descriptors}
    assert {("lateral", 0.5), ("lateral", 1.0)} <= gone
    assert not gone & {("lateral", 0.25), *(("lateral", -d) for d in LATERAL_M), *(("yaw", -a) for a in YAW_DEG)}
    assert blocked.skipped.get("pillar", 0) == len(gone)
    obstacles = Obstacles(with_pillar["obstacles"])
    for pose in blocked.poses:
        assert not obstacles.hits(footprint((pose[0, 3], pose[1, 3], _yaw(pose)), margin=CLEARANCE)).any()
    narrow = {**r["map"], "slots": [], "obstacles": [],
              "garage": {**r["map"]["garage"], "y": [base[1, 3] - 2.0, base[1, 3] + 2.0]}}
    kept = offpath_poses(r["poses"], r["frames"], [0], narrow)
    # body half width 0.9 + 0.15 m clearance: +-0.5 m stays inside +-2 m, 1 m does not; 20 deg swings the nose out
    assert {d["offset"] for d in kept.descriptors if d["kind"] == "lateral"} == {0.25, -0.25, 0.5, -0.5}
    assert {d["offset"] for d in kept.descriptors if d["kind"] == "yaw"} == {10.0, -10.0}
    assert kept.skipped == {"outside": 6}


@pytest.fixture(scope="module")
def data(tiny_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A copy of the session's tiny dataset with its off-path split, written through the CLI; only frame 0 is a
    test frame (half the off-path views: the scores, not their number, are under test)."""
    out = tmp_path_factory.mktemp("offpath") / "tiny"
    shutil.copytree(tiny_data, out)
    split = json.loads((out / "split.json").read_text())
    (out / "split.json").write_text(json.dumps({**split, "test": [0]}))
    assert main(["offpath", str(out), "--workers", "1", "--quiet"]) == 0
    return out


def test_split_is_a_dataset_of_direct_renders(data: Path) -> None:
    split = DatasetReader(data / "offpath")
    info = read_offpath(data / "offpath")
    frames = [d["frame"] for d in info["frames"]]
    assert split.frames == frames and split.split == {"train": [], "test": frames}
    assert split.has_ipm and split.has_labels and split.meta["split"] == "offpath"
    assert (data / "offpath" / "map.json").read_bytes() == (data / "map.json").read_bytes()
    renderer = SceneRenderer(get_preset("tiny"))
    for kind in ("lateral", "yaw", "manoeuvre"):
        d = next(x for x in info["frames"] if x["kind"] == kind)
        views = renderer.render(split.pose(d["frame"]).numpy(), d["frame"], exposure_frame=d["base"])
        for camera, view in views.items():
            np.testing.assert_array_equal(to_uint8(view.image), to_uint8(split.image(camera, d["frame"]).numpy()))


def test_cli_refuses_bad_input_with_one_line(data: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    before = (data / "offpath" / "offpath.json").read_bytes()
    assert main(["offpath", str(data), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "already exists" in err[0] and "--overwrite" in err[0]
    assert (data / "offpath" / "offpath.json").read_bytes() == before
    other = tmp_path / "imported"
    shutil.copytree(data, other, ignore=shutil.ignore_patterns("offpath"))
    meta = json.loads((other / "meta.json").read_text())
    (other / "meta.json").write_text(json.dumps({**meta, "generator": "parksim import"}))
    assert main(["offpath", str(other), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a `parksim synth` dataset" in err[0]
    assert main(["offpath", str(data / "offpath"), "--quiet"]) == 2
    assert "off-path split already" in capsys.readouterr().err
    assert sorted(p.name for p in other.iterdir()) == sorted(p.name for p in data.iterdir() if p.name != "offpath")


@pytest.fixture(scope="module")
def bundle(data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny photometric run of a few iterations on the split's dataset."""
    tmp = tmp_path_factory.mktemp("offpath-run")
    base = load_config("tiny")
    config = base.model_copy(update={"photometric": base.photometric.model_copy(update={"iterations": 4})})
    (tmp / "c.yaml").write_text(dump_config(config))
    return reconstruct(data, tmp / "run", tmp / "c.yaml", log=lambda s: None)


def test_eval_writes_the_offpath_table_and_plot(bundle: Path, data: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "eval"
    assert main(["eval", str(bundle), str(data), "-o", str(out), "--backend", "numba"]) == 0
    assert "offpath.png" in capsys.readouterr().out
    result = json.loads((out / "eval.json").read_text())
    off = result["offpath"]
    descriptors = read_offpath(data / "offpath")["frames"]
    groups = group_frames(descriptors)
    assert [g["group"] for g in off["groups"]] == list(groups)
    assert sum(g["views"] for g in off["groups"]) == 4 * len(descriptors) == len(off["views"])
    assert off["on_path"]["psnr"] == pytest.approx(result["overall"]["psnr"])
    lateral = [v["psnr"] for v in off["views"] if v["kind"] == "lateral" and abs(v["offset"]) == 0.25]
    first = next(g for g in off["groups"] if g["group"] == "lateral ±0.25 m")
    assert first["psnr"] == pytest.approx(sum(lateral) / len(lateral))
    text = (out / "eval.md").read_text()
    assert "| on path (recorded test frames) |" in text and "| manoeuvre into slot |" in text
    assert f"| lateral ±0.25 m | {first['frames']} | {first['views']} | {first['psnr']:.2f} |" in text
    assert (out / "offpath.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["eval", str(bundle), str(data), "-o", str(tmp_path / "plain"), "--no-offpath",
                 "--backend", "numba"]) == 0
    assert "offpath" not in json.loads((tmp_path / "plain" / "eval.json").read_text())


def test_paper_tables_score_detection_per_offset_group(bundle: Path, data: Path, tmp_path: Path) -> None:
    detector = train_detector([data], tmp_path / "dmpr", TrainOptions(steps=2, batch_size=2, input_size=64,
                                                                     threads=1), progress=False).parent
    result = evaluate_runs([(bundle, None)], data, {"dmpr": load_detector(detector)}, tmp_path / "tables",
                           backend="numba", decode=DecodeOptions(threshold=0.3))
    off, run = result["offpath"], result["runs"][0]
    split = DatasetReader(data / "offpath")
    labelled = sum(len(split.labels(f)["slots"]) for f in split.frames)
    assert sum(off["gt"]["dmpr"][g["group"]]["slots"]["labelled"] for g in off["groups"]) == labelled
    assert set(run["offpath"]["detection"]["dmpr"]) == set(run["offpath"]["quality"]) == {
        g["group"] for g in off["groups"]}
    text = (tmp_path / "tables" / "tables.md").read_text()
    assert "### DMPR-PS off the recorded path, tiny" in text and "| manoeuvre into slot |" in text
