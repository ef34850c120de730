"""``SynthConfig``: every knob of the synthetic studio, with presets ``quick`` and ``default``.

CLI flags of ``uvatar synth`` map one-to-one onto these fields (no second source of defaults).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

from uvatar.capture.synth.appearance import AppearanceConfig
from uvatar.capture.synth.cameras import StudioConfig
from uvatar.capture.synth.clothing import ClothingConfig
from uvatar.capture.synth.lighting import LightConfig
from uvatar.capture.synth.motion import MotionConfig
from uvatar.errors import check_values

__all__ = ["SynthConfig", "PRESETS", "preset", "BYSTANDER_PATHS", "BYSTANDER_LOOKS"]

BYSTANDER_PATHS = ("circle", "cross")
BYSTANDER_LOOKS = ("own", "subject")


@dataclass(frozen=True)
class SynthConfig:
    """frames: total frames (takes + held-out); cameras: multi-view cameras (0: no images);
    image_size: square image side (px); scan_texture: scan atlas side (texels); gt_texels: side of
    the ground-truth maps in body UV space; fit_noise_deg: per-joint fit noise (degrees);
    fit_tracks: which joints the fits track: "body" (the body model's conditioning joints, as
    body-only capture fits do: SMPL and EasyMocap's smpl fits carry no finger articulation, so the
    fitted fingers, toes and eyes stay in the rest pose while the scanned performer's curl) or "all"
    (every joint, with noise);
    heldout: held-out frames at the end (None: 10 % of frames when there are at least 10);
    seed: everything is a deterministic function of it; workers: processes (1: in-process);
    segment_frames: mean frames per scan topology (each drawn in +-20 %); face_count: range of scan
    face counts; subdivision_levels: template subdivisions before decimation; broken_every: about one
    broken frame per this many (at least one when frames >= 20); broken_fraction: range of the
    surface fraction cut away; scan_noise: scan vertex noise along the normal (m); chart_area:
    max xatlas chart area (m^2); background: image background grey level; preview: write
    OUT/preview.png; bystanders: more people in the images (:mod:`.bystanders`); bystander_path:
    "circle" (a circle of 1.1 m around the subject) or "cross" (the hard case: each bystander, of the
    subject's height, crosses in front of the subject, stays within 0.5 m of it, then passes behind);
    bystander_look: "own" (other clothes) or "subject" (the subject's clothes colours); light: "studio" (the
    fixed key/fill/ambient rig with cast shadows and ambient occlusion baked into every frame's
    texture, :mod:`.lighting`, set by ``lighting``) or "none" (unlit: albedo times creases, as
    captures made before the rig)."""

    frames: int = 100
    cameras: int = 8
    image_size: int = 512
    scan_texture: int = 1024
    gt_texels: int = 256
    fit_noise_deg: float = 2.0
    fit_tracks: str = "body"
    heldout: int | None = None
    seed: int = 0
    workers: int = 2
    segment_frames: int = 25
    face_count: tuple[int, int] = (50_000, 150_000)
    subdivision_levels: int = 2
    broken_every: int = 20
    broken_fraction: tuple[float, float] = (0.5, 0.65)
    scan_noise: float = 0.0006
    chart_area: float = 0.02
    background: float = 1.0
    body_model: str = "anny"
    preview: bool = True
    bystanders: int = 0
    bystander_path: str = "circle"
    bystander_look: str = "own"
    light: str = "studio"
    motion: MotionConfig = field(default_factory=MotionConfig)
    appearance: AppearanceConfig = field(default_factory=AppearanceConfig)
    clothing: ClothingConfig = field(default_factory=ClothingConfig)
    studio: StudioConfig = field(default_factory=StudioConfig)
    lighting: LightConfig = field(default_factory=LightConfig)

    def __post_init__(self) -> None:
        check_values([
            (self.frames >= 1, f"frames must be at least 1, got {self.frames}"),
            (self.cameras >= 0, f"cameras must not be negative, got {self.cameras}"),
            (self.image_size >= 1, f"image_size must be at least 1, got {self.image_size}"),
            (self.scan_texture >= 1, f"scan_texture must be at least 1, got {self.scan_texture}"),
            (self.gt_texels >= 1, f"gt_texels must be at least 1, got {self.gt_texels}"),
            (self.fit_noise_deg >= 0, f"fit_noise_deg must not be negative, got {self.fit_noise_deg}"),
            (self.fit_tracks in ("body", "all"), f"fit_tracks must be 'body' or 'all', got {self.fit_tracks!r}"),
            (self.light in ("studio", "none"), f"light must be 'studio' or 'none', got {self.light!r}"),
            (self.heldout is None or self.heldout >= 0, f"heldout must not be negative, got {self.heldout}"),
            (self.workers >= 1, f"workers must be at least 1, got {self.workers}"),
            (self.bystander_path in BYSTANDER_PATHS,
             f"bystander_path must be one of {', '.join(BYSTANDER_PATHS)}, got {self.bystander_path!r}"),
            (self.bystander_look in BYSTANDER_LOOKS,
             f"bystander_look must be one of {', '.join(BYSTANDER_LOOKS)}, got {self.bystander_look!r}"),
            (self.bystanders >= 0, f"bystanders must not be negative, got {self.bystanders}")])

    def heldout_count(self) -> int:
        if self.heldout is not None:
            return max(0, min(int(self.heldout), int(self.frames) - 1))
        return int(self.frames) // 10 if self.frames >= 10 else 0

    def replace(self, **changes) -> SynthConfig:
        return replace(self, **changes)

    def to_dict(self) -> dict:
        return asdict(self)


PRESETS = {
    "default": SynthConfig(),
    # tests and demo smoke runs: seconds, not minutes
    "quick": SynthConfig(frames=8, cameras=2, image_size=64, scan_texture=128, gt_texels=64, workers=1,
                         segment_frames=4, face_count=(6_000, 12_000), subdivision_levels=1,
                         # the light on the template itself, 32 AO rays: ~0.6 s per frame instead of ~4
                         lighting=LightConfig(ao_rays=32, occluder_levels=0)),
}


def preset(name: str, **overrides) -> SynthConfig:
    """A named preset with fields overridden (``None`` values are ignored)."""
    if name not in PRESETS:
        raise ValueError(f"unknown synth preset {name!r}; choose one of {', '.join(PRESETS)}")
    return PRESETS[name].replace(**{k: v for k, v in overrides.items() if v is not None})
