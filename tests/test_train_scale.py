"""Training-time image scale (``data.image_scale``): the ``cpu_real`` preset, half-size training end to end, scale 1
bit for bit the default path, bad values one config error."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import yaml

from parksim.bundle import load
from parksim.cli import main
from parksim.data import DatasetReader
from parksim.recon.config import PRESETS_DIR, ConfigError, load_config, parse_config
from parksim.recon.evaluate import evaluate_bundle
from parksim.recon.reconstruct import reconstruct
from parksim.recon.trainer import Trainer

TENSORS = ("means", "quats", "log_scales", "opacity_logits", "sh")


def _tiny_with(tmp_path: Path, name: str, **sections: dict) -> Path:
    """The ``tiny`` preset with ``sections`` merged in, written as ``name``.yaml."""
    data = yaml.safe_load((PRESETS_DIR / "tiny.yaml").read_text())
    for key, values in sections.items():
        data[key] = {**data.get(key, {}), **values}
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_cpu_real_preset_validates_and_trains_smaller() -> None:
    config = load_config("cpu_real")
    assert 0 < config.data.image_scale < 1
    assert config.pose_opt.enabled is True and config.lr.response > 0 and config.run.device == "cpu"


@pytest.mark.parametrize("value", [0, 1.5])
def test_bad_image_scale_is_one_config_error(value: float, tmp_path: Path, tiny_data: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ConfigError, match=r"data\.image_scale"):
        parse_config({"data": {"image_scale": value}}, "x.yaml")
    bad = _tiny_with(tmp_path, "bad", data={"image_scale": value})
    assert main(["reconstruct", str(tiny_data), "-o", str(tmp_path / "run"), "--config", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert "data.image_scale" in err and "\n" not in err
    assert not (tmp_path / "run").exists()


def test_half_scale_trains_on_half_size_images_and_keeps_the_full_rig(tiny_data: Path, tmp_path: Path) -> None:
    config_path = _tiny_with(tmp_path, "half", data={"image_scale": 0.5}, pose_opt={"enabled": True})
    reader = DatasetReader(tiny_data)
    trainer = Trainer(reader, load_config(config_path), tmp_path / "probe", log=lambda s: None)
    trainer.decode_inputs()
    for (frame, camera), image in trainer._images.items():
        full = reader.rig.cameras[camera].model
        assert image.shape == (full.height // 2, full.width // 2, 3)
        assert trainer.rig.cameras[camera].model.width == full.width // 2
        assert trainer.masks[camera].shape[-2:] == image.shape[:2]
        assert torch.allclose(image.mean(dim=(0, 1)), reader.image(camera, frame).mean(dim=(0, 1)), atol=2e-3)

    out = reconstruct(tiny_data, tmp_path / "run", config_path, log=lambda s: None)
    bundle = load(out)
    assert bundle.meta["image_scale"] == 0.5
    for name, cam in bundle.rig.cameras.items():
        full = reader.rig.cameras[name].model
        assert (cam.model.width, cam.model.height) == (full.width, full.height)
        assert float(cam.model.fx) == float(full.fx)

    trained = evaluate_bundle(out, tiny_data, tmp_path / "eval")
    assert trained["image_scale"] == 0.5 and trained["overall"]["psnr"] > 10
    full_size = evaluate_bundle(out, tiny_data, tmp_path / "eval_full", image_scale=1.0)
    assert full_size["image_scale"] == 1.0 and full_size["overall"]["psnr"] > 10


def test_scale_one_is_bit_identical_to_the_default(tiny_data: Path, tmp_path: Path) -> None:
    default = reconstruct(tiny_data, tmp_path / "default", "tiny", log=lambda s: None)
    one = reconstruct(tiny_data, tmp_path / "one", _tiny_with(tmp_path, "one", data={"image_scale": 1.0}),
                      log=lambda s: None)
    a, b = load(default), load(one)
    for name in TENSORS:
        assert torch.equal(getattr(a.scene, name), getattr(b.scene, name)), name
    assert a.meta["camera_response"] == b.meta["camera_response"]
