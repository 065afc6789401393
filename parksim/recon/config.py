"""Training configuration: pydantic models (unknown keys are errors) loaded from YAML files.

The defaults are the paper's numbers (ParkGaussian on 3DGS/3DGUT + gsplat's MCMC strategy);
the packaged preset ``parkgaussian`` spells them out and shorter CPU schedules override them.
Presets ship inside the package (``parksim/configs/NAME.yaml``), so ``--config tiny`` works from any folder.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from .slot_aware.config import SlotAwareConfig

__all__ = ["TrainConfig", "DataConfig", "PoseRefineConfig", "ConfigError", "PRESETS_DIR", "preset_names",
           "resolve_config", "load_config", "parse_config", "dump_config"]

PRESETS_DIR = Path(__file__).resolve().parents[1] / "configs"
"""The packaged training presets, one YAML file per name."""


class ConfigError(ValueError):
    """A config file is missing, not YAML, or does not validate; the message names the file and the keys."""


class _Strict(BaseModel):
    """Base model: a key that is not a field is an error (a typo must not become a silent default)."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class LearningRates(_Strict):
    """Adam learning rates per attribute (3DGS values); ``means`` is multiplied by the scene extent."""

    means: float = Field(1.6e-4, gt=0)
    means_final_factor: float = Field(0.01, gt=0, le=1, description="position lr decays exponentially to this fraction")
    sh0: float = Field(2.5e-3, gt=0)
    shN: float = Field(2.5e-3 / 20, gt=0)
    opacity: float = Field(0.05, gt=0)
    scales: float = Field(5e-3, gt=0)
    quats: float = Field(1e-3, gt=0)
    response: float = Field(1e-3, ge=0, description="per-camera gain and vignetting (0 disables them)")
    exposure: float = Field(0.0, ge=0, description="per-image (frame, camera) RGB gain and bias for auto-exposure "
                            "and white balance, applied in training only (0: off; docs/training.md measures 3e-3)")


class DataConfig(_Strict):
    """How the dataset's images are seen in training (and by ``parksim eval`` of the bundle)."""

    image_scale: float = Field(1.0, gt=0, le=1, description="train on the images resized by this factor "
                               "(cv2 INTER_AREA) against the rig's cameras scaled to match (CameraModel.scaled): "
                               "0.5 quarters the pixels of each step; the bundle keeps the full-size rig and "
                               "`parksim eval` scores at this scale unless told otherwise")


class InitConfig(_Strict):
    """Where the initial Gaussians come from and how they start."""

    source: Literal["auto", "points", "colmap", "random"] = "auto"
    colmap_model: str | None = Field(None, description="COLMAP sparse model folder (source=colmap)")
    random_count: int = Field(100_000, gt=0)
    max_points: int = Field(1_000_000, gt=0, description="subsample larger point clouds to this many")
    opacity: float = Field(0.5, gt=0, lt=1)
    scale_factor: float = Field(1.0, gt=0, description="initial scale = this x mean distance to 3 nearest points")


class MCMCConfig(_Strict):
    """3DGS-MCMC (Kheradmand et al.) as in gsplat's MCMCStrategy."""

    cap_max: int = Field(1_000_000, gt=0)
    grow_rate: float = Field(0.05, ge=0)
    noise_lr: float = Field(5e5, ge=0)
    refine_start: int = Field(500, ge=0)
    refine_stop: int = Field(25_000, ge=0)
    refine_every: int = Field(100, gt=0)
    min_opacity: float = Field(0.005, gt=0, lt=1)
    opacity_reg: float = Field(0.01, ge=0)
    scale_reg: float = Field(0.01, ge=0)


class ADCConfig(_Strict):
    """Adaptive density control of the original 3DGS (clone, split, prune, opacity reset)."""

    grad_threshold: float = Field(2e-4, gt=0)
    percent_dense: float = Field(0.01, gt=0)
    refine_start: int = Field(500, ge=0)
    refine_stop: int = Field(15_000, ge=0)
    refine_every: int = Field(100, gt=0)
    reset_every: int = Field(3000, gt=0)
    min_opacity: float = Field(0.005, gt=0, lt=1)
    max_screen_fraction: float = Field(0.1, gt=0, description="prune Gaussians larger than this x scene extent")
    cap_max: int = Field(3_000_000, gt=0)


class DensifyConfig(_Strict):
    """Densification strategy: the paper's MCMC by default, 3DGS ADC as the alternative."""

    strategy: Literal["mcmc", "adc"] = "mcmc"
    mcmc: MCMCConfig = MCMCConfig()
    adc: ADCConfig = ADCConfig()


class PhotometricConfig(_Strict):
    """Phase 1: (1 - lambda) L1 + lambda D-SSIM on the fisheye images, masked to the valid pixels."""

    iterations: int = Field(20_000, ge=0)
    ssim_lambda: float = Field(0.2, ge=0, le=1)
    sh_degree: int = Field(3, ge=0, le=3)
    sh_degree_interval: int = Field(1000, ge=0, description="raise the SH degree by one every this many iterations "
                                    "(0: the full degree from the first, as fine-tuning needs)")


class RunConfig(_Strict):
    """Run mechanics: seed, device, batch, renderer, logging and checkpoint cadence."""

    seed: int = 0
    device: str = Field("cpu", pattern=r"^(auto|cpu|cuda(:[0-9]+)?)$",
                        description="where to train: cpu, cuda[:N], or auto (a CUDA GPU when there is one and the "
                                    "CUDA extra is installed); `--device` overrides it; not part of what a resume "
                                    "or --from compares, so a run may continue on another device")
    batch_size: int = Field(1, gt=0, description="(frame, camera) views rendered per iteration")
    backend: Literal["auto", "torch", "numba"] = "auto"
    projection: Literal["ut", "ewa"] = Field("ut", description="2D footprints: the unscented transform through the "
                                             "exact lens (ParkGaussian, 3DGUT) or the first-order Jacobian (EWA: "
                                             "vanilla 3DGS through a fisheye Jacobian, as FisheyeGS); a baseline knob")
    log_every: int = Field(10, gt=0)
    checkpoint_every: int = Field(1000, gt=0)
    eval_every: int = Field(0, ge=0, description="test-frame PSNR/SSIM every this many iterations (0: never)")
    eval_stride: int = Field(1, gt=0, description="use every n-th test view in periodic evaluation")
    progress: bool = True


class PoseRefineConfig(_Strict):
    """Learned corrections of the ego (or per-image) poses and the extrinsics (``parksim.recon.pose_refine``).

    ``enabled: auto`` turns them on exactly for imported recordings (meta.json ``source: import``): real odometry
    and calibration are never exact, synthetic ones are. Rotations in rad, translations in m, per Adam step.
    """

    enabled: Literal["auto"] | bool = "auto"
    extrinsics: bool = Field(True, description="also refine each camera's T_vehicle_camera (ego datasets)")
    lr: float = Field(1e-3, gt=0, description="Adam lr of the corrections (nerfstudio: 6e-4, gsplat: 1e-5)")
    lr_final_factor: float = Field(0.01, gt=0, le=1, description="lr decays exponentially to this fraction")
    weight_decay: float = Field(1e-6, ge=0, description="Adam (L2) weight decay pulling corrections to identity")
    test_steps: int = Field(100, ge=0, description="evaluation: test-time pose alignment steps (0: none)")
    test_lr: float = Field(5e-3, gt=0, description="Adam lr of test-time alignment (decays by lr_final_factor); "
                           "an Adam step moves each coordinate by about lr, so it reaches about 0.2 * test_lr * "
                           "test_steps (10 cm, 6 deg)")


class TrainConfig(_Strict):
    """Everything ``parksim reconstruct`` needs besides the data.

    Attributes:
        run: seed, device, batch, renderer, logging and checkpoint cadence.
        data: the training image scale.
        init: where the initial Gaussians come from.
        lr: Adam learning rates per attribute.
        photometric: phase 1 (L1 + D-SSIM on the fisheye images).
        slot_aware: phase 2 (slot-aware losses on the BEV).
        densify: densification strategy (MCMC or ADC).
        pose_opt: learned pose and extrinsics corrections.

    Example:
        >>> TrainConfig().schedule_iterations, load_config("tiny").run.seed
        (30000, 0)
    """

    run: RunConfig = RunConfig()
    data: DataConfig = DataConfig()
    init: InitConfig = InitConfig()
    lr: LearningRates = LearningRates()
    photometric: PhotometricConfig = PhotometricConfig()
    slot_aware: SlotAwareConfig = Field(SlotAwareConfig(), description="phase 2; its iterations count in the "
                                        "learning-rate schedule (phase 1 + phase 2 = the paper's 30k)")
    densify: DensifyConfig = DensifyConfig()
    pose_opt: PoseRefineConfig = PoseRefineConfig()

    @model_validator(mode="after")
    def _ut_for_slot_aware(self) -> TrainConfig:
        """The slot-aware phase renders with the unscented transform; EWA is a photometric-only baseline."""
        if self.run.projection != "ut" and self.slot_aware.iterations:
            raise ValueError("run.projection: ewa is a photometric-only baseline; set slot_aware.iterations: 0")
        return self

    @property
    def schedule_iterations(self) -> int:
        """Length of the learning-rate schedule: both phases."""
        return self.photometric.iterations + self.slot_aware.iterations

    def on_device(self, device: str) -> TrainConfig:
        """This config with ``run.device`` set to ``device`` (the ``--device`` override).

        Args:
            device: ``auto``, ``cpu`` or ``cuda[:N]``.

        Returns:
            A copy.

        Raises:
            ValidationError: ``device`` is not one of those names.
        """
        run = RunConfig.model_validate({**self.run.model_dump(), "device": device})
        return self.model_copy(update={"run": run})

    def same_run(self, other: TrainConfig) -> bool:
        """Whether ``other`` trains the same run: equal in everything but ``run.device``.

        Where a run trains does not change what it trains, so a checkpoint written on a GPU resumes on the CPU and
        the other way round.

        Args:
            other: the config to compare (a checkpoint's, a run folder's).

        Returns:
            True when they differ at most in ``run.device``.
        """
        return self.on_device("cpu") == other.on_device("cpu")


def _format_errors(err: ValidationError) -> str:
    """One line per problem: dotted key path and pydantic's message."""
    def one(e: Any) -> str:
        where = ".".join(str(p) for p in e["loc"])
        return f"{where}: {e['msg']}" if where else str(e["msg"]).removeprefix("Value error, ")

    return "; ".join(one(e) for e in err.errors())


def parse_config(data: object, source: str) -> TrainConfig:
    """Validate a mapping as a ``TrainConfig``; ``source`` names it in errors.

    Args:
        data: the parsed YAML (None counts as empty: all defaults).
        source: what to name in error messages (the file).

    Returns:
        The validated config.

    Raises:
        ConfigError: not a mapping, or a key or value the models refuse (one ``key.path: message`` per problem).
    """
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping at the top level, got {type(data).__name__}")
    try:
        return TrainConfig.model_validate(data)
    except ValidationError as e:
        raise ConfigError(f"{source}: invalid config: {_format_errors(e)}") from None


def preset_names() -> list[str]:
    """Names of the packaged presets (``tiny``, ``demo``, ``cpu_fast``, ...), sorted.

    Returns:
        The YAML file stems under ``PRESETS_DIR``.
    """
    return sorted(p.stem for p in PRESETS_DIR.glob("*.yaml"))


def resolve_config(spec: str | Path) -> Path:
    """The YAML file that ``spec`` names: an existing file path, else a packaged preset by name.

    A path wins over a preset of the same name, so a user's ``tiny.yaml`` in the working folder is theirs.

    Args:
        spec: a file path, or a preset name (with or without ``.yaml``).

    Returns:
        The YAML file.

    Raises:
        ConfigError: neither an existing file nor a packaged preset.
    """
    path = Path(spec)
    if path.is_file():
        return path
    preset = PRESETS_DIR / f"{path.stem if path.suffix in ('.yaml', '.yml') else path.name}.yaml"
    if path.parent == Path(".") and preset.is_file():
        return preset
    raise ConfigError(f"{spec}: neither a config file nor a packaged preset (presets: {', '.join(preset_names())})")


def load_config(path: str | Path) -> TrainConfig:
    """Read and validate a YAML config file, given by path or by packaged preset name.

    Args:
        path: a YAML file or a preset name (``resolve_config``).

    Returns:
        The validated config.

    Raises:
        ConfigError: the file is missing, not YAML, or does not validate.
    """
    path = resolve_config(path)
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML: {' '.join(str(e).split())}") from None
    return parse_config(data, str(path))


def dump_config(config: TrainConfig) -> str:
    """The config as YAML text (every field, so the file documents the run).

    Args:
        config: the config.

    Returns:
        YAML that ``load_config`` reads back to an equal config.
    """
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)
