"""The DVA model: LBS-articulated primitives + texel-aligned features -> decoders -> ray marching.

``DvaModel(cfg, template, conditioning_joints)`` holds everything learned; the body model that poses the
template lives outside (the trainer / renderer calls ``body.pose`` and passes posed vertices in).
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn as nn

from uvatar.dva.corrections import CorrectionConfig
from uvatar.dva.decoders import DecoderConfig, DvaDecoder
from uvatar.dva.features import (
    FeatureConfig,
    ImageEncoder,
    PoseEncoder,
    pose_feature_maps,
    texel_skin_weights,
    texture_at_voxels,
    view_feature_map,
    voxel_uv_grid,
)
from uvatar.dva.losses import LossConfig
from uvatar.dva.primitives import PrimitiveConfig, apply_correctives, articulated_frames, build_uv_grid
from uvatar.dva.raymarch import raymarch
from uvatar.dva.raymarch_ref import Primitives, RaymarchConfig
from uvatar.errors import check_values
from uvatar.precision import PRECISIONS, compile_mode_check, precision_check

BACKGROUNDS = ("mask", "photo", "random")


class EncodeDecode(nn.Module):
    """(pose maps (B, 3 Jc, W, W), image texture (B, 4, R, R), view features (B, 1, W, W), colour skip
    or None) -> motion (B, 9, W, W) fp32, the marcher's payload (B, K, 4, S, S, S) fp32: a
    :class:`DvaModel`'s encoders and decoders in one module (what the fast paths compile), under
    autocast in ``dtype`` when that is not fp32. Holds the model's own encoders and decoder (no copies).

    channels_last: NHWC convolution inputs. cache: autocast's weight cache (off under a CUDA graph
    capture, torch.cuda.graph's documented requirement). Used by :class:`~uvatar.dva.frame.FrameRenderer`
    and by training's compact step (:meth:`DvaModel.forward` with ``decode``)."""

    def __init__(self, model, dtype: torch.dtype = torch.float32, channels_last: bool = False, cache: bool = True):
        super().__init__()
        self.pose_encoder, self.image_encoder, self.decoder = model.pose_encoder, model.image_encoder, model.decoder
        self.dtype, self.channels_last, self.cache = dtype, channels_last, cache

    def forward(self, pose_maps, image_texture, f_view, skip_colour=None, skip_weight=None):
        if self.channels_last:
            pose_maps, image_texture, f_view = (t.contiguous(memory_format=torch.channels_last)
                                                for t in (pose_maps, image_texture, f_view))
        with torch.autocast(pose_maps.device.type, dtype=self.dtype, enabled=self.dtype != torch.float32,
                            cache_enabled=self.cache):
            f_pose = self.pose_encoder(pose_maps)
            f_img = self.image_encoder(image_texture)
            skip = None if skip_colour is None else (skip_colour, skip_weight)
            motion, payload = self.decoder.payload(f_pose, f_img, f_view, skip, torch.float32)
        return motion.float(), payload


@dataclass
class TrainConfig:
    """lr: Adam learning rate. batch: (frame, camera) samples per step. patch: side of the square pixel
    crop rendered per sample. warmup_iters: correctives stay off before this step. all_views_iters:
    curriculum stage 1 (image features from every training view) length; afterwards ``driving_views``
    random views. checkpoint_every: steps between checkpoints. The learning rate decays exponentially to
    ``lr * lr_final`` over the last ``1 - lr_decay_start`` of the run (by steps or by minutes, whichever
    is further along). background: what the render is compared with outside the person's mask: "mask"
    replaces the photo there by the camera's background colour (the colour the render is composited
    over), so a cluttered real room is not something the primitives must learn (as Neural Body trains
    on masked photos); "photo" compares with the raw photo (a studio's clean backdrop); "random" is
    "mask" with a new uniformly random colour per sample and step in place of the camera's, so a
    half-transparent render can never pass for the person's colour blended with a known backdrop
    (the opacity must match the mask; a common NeRF / Gaussian-avatar practice).
    precision: autocast type of the encoders and decoders in a step ("fp32", "bf16", "fp16"; the
    geometry, the marcher and the loss stay fp32): "bf16" on a GPU halves the decoders' slabs.
    hide_target_view: the image input of a sample leaves out the camera it is scored in, as at test
    time, where the held-out camera never drives (with 3 training cameras and ``driving_views`` 3 the
    target's own photo is otherwise always in its input, and the colour skip learns to copy it).
    pairs_per_ray: the Warp marcher's (ray, primitive) pair buffer per rendered ray
    (:class:`~uvatar.dva.raymarch_warp.PairBudget`), so that a step reads no pair count back; a step that
    needed more is reported (a warning, at most a step late) and the buffer grows; 0: the exact buffer
    (a read-back per sample). compile: the step's encoders and decoders go through ``torch.compile``
    (:class:`EncodeDecode`; compile_mode "reduce-overhead" adds CUDA graphs on a GPU, "max-autotune"
    searches kernels); channels_last: the step's convolutions in NHWC (what tensor cores take without
    a layout conversion per convolution on a GPU). Both are how a run computes, not what it learns: a
    resumed run takes the caller's. Off by default (compile: minutes of compilation on a small CPU);
    the colour skip's steps use neither. graph: capture the whole step (forward, loss, backward, update)
    in a CUDA graph and replay it (:class:`~uvatar.dva.train_step.StepGraph`; CUDA, the Warp marcher and
    one process; elsewhere the steps run eagerly and say so), also how a run computes."""

    lr: float = 2e-3
    lr_decay_start: float = 0.6
    lr_final: float = 0.1
    batch: int = 2
    patch: int = 48
    warmup_iters: int = 300
    all_views_iters: int = 1000
    driving_views: int = 3
    checkpoint_every: int = 200
    iters: int = 100_000
    minutes: float = 18.0
    background: str = "mask"
    hide_target_view: bool = False
    precision: str = "fp32"
    pairs_per_ray: float = 64.0
    compile: bool = False
    compile_mode: str = "default"
    channels_last: bool = False
    graph: bool = False

    def __post_init__(self) -> None:
        check_values([(self.background in BACKGROUNDS,
                       f"background must be one of {BACKGROUNDS}, got {self.background!r}"),
                      precision_check(self.precision), compile_mode_check(self.compile_mode),
                      (not (self.graph and self.compile and self.compile_mode in ("reduce-overhead", "max-autotune")),
                       f"graph=True captures the whole step: compile_mode {self.compile_mode!r} (CUDA graphs of "
                       "its own) cannot nest in it; use compile_mode 'default'")])


@dataclass
class DvaConfig:
    primitives: PrimitiveConfig = field(default_factory=PrimitiveConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)
    decoder: DecoderConfig = field(default_factory=DecoderConfig)
    raymarch: RaymarchConfig = field(default_factory=RaymarchConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    corrections: CorrectionConfig = field(default_factory=CorrectionConfig)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> DvaConfig:
        kinds = {"primitives": PrimitiveConfig, "features": FeatureConfig, "decoder": DecoderConfig,
                 "raymarch": RaymarchConfig, "loss": LossConfig, "train": TrainConfig,
                 "corrections": CorrectionConfig}
        if "corrections" not in d:  # a run from before the corrections: trained without them
            d = {**d, "corrections": {"pose": False, "colour": False}}
        train = d.get("train")
        if train is not None and "background" not in train:  # a run from before the option: raw photo
            d = {**d, "train": {**train, "background": "photo"}}
        prims = d.get("primitives")
        if prims is not None and "min_scale_corrective" not in prims:  # before the option: -2
            d = {**d, "primitives": {**prims, "min_scale_corrective": -2.0}}
        feats = d.get("features")
        if feats is not None and "image_centred" not in feats:  # before the option: leaky last layer
            d = {**d, "features": {**feats, "image_centred": False}}
            feats = d["features"]
        if feats is not None and "colour_skip" not in feats:  # before the colour skip: trained without it
            d = {**d, "features": {**feats, "colour_skip": False}}
        loss = d.get("loss")
        if loss is not None and "motion" not in loss:  # before the motion prior: trained without it
            d = {**d, "loss": {**loss, "motion": 0.0}}
            loss = d["loss"]
        if loss is not None and "colour_tv" not in loss:  # before the colour smoothness: trained without it
            d = {**d, "loss": {**loss, "colour_tv": 0.0}}
            loss = d["loss"]
        if loss is not None and "beta_outside_mask" not in loss:  # before the option: the prior everywhere
            d = {**d, "loss": {**loss, "beta_outside_mask": False}}
        dec = d.get("decoder")
        if dec is not None and "depth_colour" not in dec:  # before the option: colour in every voxel
            d = {**d, "decoder": {**dec, "depth_colour": True}}
        return cls(**{k: kinds[k](**v) for k, v in d.items() if k in kinds})


def _preset(grid, voxels, hidden, step, pose_ch=16, img_ch=16, primitives=None, loss=None, **train) -> DvaConfig:
    """A :class:`DvaConfig` of the given sizes; ``primitives`` / ``loss``: PrimitiveConfig / LossConfig
    fields replacing their defaults; ``train``: TrainConfig fields."""
    cfg = DvaConfig()
    cfg.primitives = dataclasses.replace(cfg.primitives, grid=grid, **(primitives or {}))
    cfg.decoder.voxels = voxels
    cfg.decoder.hidden = hidden
    cfg.raymarch.step = step
    cfg.features.pose_channels = pose_ch
    cfg.features.image_channels = img_ch
    cfg.train = dataclasses.replace(cfg.train, **train)
    cfg.loss = dataclasses.replace(cfg.loss, **(loss or {}))
    return cfg


PRESETS = {
    # the paper: K = 4096 primitives of 16^3 voxels (GPU territory)
    "paper": _preset(64, 16, 256, 0.005, 64, 64, batch=4, patch=128, lr=5e-4, warmup_iters=2000,
                     all_views_iters=1000, minutes=24 * 60.0),
    # a 2-core CPU in ~20 minutes: K = 2304 primitives of 4^3 voxels, the SSIM term at 0.4, the colour
    # smoothness at 0.3 and boxes never smaller than their rest size (no seams), the best of runs 35-51
    # on the real recording (docs/real.md); the voxel slab is 192^2 texels as at K = 576 of 8^3 (the
    # preset from the fused marcher until 2026-11-26, the largest grid of 8^3 whose step took no longer
    # than K = 256's with the torch marcher), so a step costs the same
    "cpu": _preset(48, 4, 32, 0.012, primitives={"min_scale_corrective": 0.0},
                   loss={"ssim": 0.4, "colour_tv": 0.3}),
    # unit tests and smoke runs
    "tiny": _preset(8, 4, 8, 0.03, 4, 4, batch=1, patch=16, warmup_iters=2, all_views_iters=3,
                    checkpoint_every=2, minutes=1.0),
}


def preset(name: str) -> DvaConfig:
    from uvatar.errors import InputError

    if name not in PRESETS:
        raise InputError("preset", f"unknown preset {name!r}; choose from {sorted(PRESETS)}")
    return copy.deepcopy(PRESETS[name])


@dataclass
class DvaOutput:
    """Decoded primitives for a batch: positions (B,K,3), rotations (B,K,3,3), scales (B,K,3),
    payload (B,K,4,S,S,S) (RGB + density), motion (B,9,W,W) raw correctives, learned_rgb
    (B,K,3,S,S,S): the decoder's own colour, before the colour skip adds the photos' (the payload's
    RGB when there is none)."""

    positions: torch.Tensor
    rotations: torch.Tensor
    scales: torch.Tensor
    payload: torch.Tensor
    motion: torch.Tensor
    learned_rgb: torch.Tensor
    _samples: tuple | None = field(default=None, init=False, repr=False, compare=False)

    def primitives(self, b: int) -> Primitives:
        """Sample ``b``'s primitives: views of the batch made by one ``unbind`` per tensor for every
        sample (on the first call). Its backward writes each sample's gradient into one batch-sized
        gradient; indexing each sample (``payload[b]``) would make a zero-filled batch-sized gradient per
        sample and add them up (a training step at the paper's scale: 1 GB of payload, B times)."""
        if self._samples is None:
            self._samples = tuple(zip(*(t.unbind(0) for t in (self.positions, self.rotations, self.scales,
                                                              self.payload)), strict=True))
        return Primitives(*self._samples[b])


class DvaModel(nn.Module):
    """forward(posed_vertices (B,V,3), joint_rotvecs (B,J,3), image_texture (B,4,R,R),
    camera_centers (B,3)) -> DvaOutput. ``R = W * cfg.features.image_scale`` (see :attr:`image_raster`)."""

    def __init__(self, cfg: DvaConfig, template, conditioning_joints):
        super().__init__()
        from uvatar.geometry import rasterize_uv

        self.cfg = cfg
        self.template = template
        self.joints = tuple(int(j) for j in conditioning_joints)
        self.grid = build_uv_grid(template, cfg.primitives)
        W = self.grid.size
        self.image_raster = rasterize_uv(template.uvs, template.uv_faces, W * cfg.features.image_scale)
        self.register_buffer("texel_weights", torch.as_tensor(
            texel_skin_weights(self.grid.raster, template, self.joints)))
        self.register_buffer("rest_scales", torch.as_tensor(self.grid.rest_scales))
        self.register_buffer("correctives_on", torch.zeros((), dtype=torch.bool))
        self.register_buffer("joint_index", torch.tensor(self.joints, dtype=torch.long), persistent=False)
        f = cfg.features
        self.pose_encoder = PoseEncoder(len(self.joints), f.pose_channels)
        self.image_encoder = ImageEncoder(f.image_scale, f.image_channels, centred=f.image_centred)
        self.decoder = DvaDecoder(cfg.decoder, W, f.pose_channels, f.image_channels, 1, f.colour_skip)
        if f.colour_skip:
            self.register_buffer("voxel_uv", torch.as_tensor(voxel_uv_grid(
                self.grid.raster, template, cfg.decoder.voxels, cfg.primitives.scale_factor)), persistent=False)

    def forward(self, posed_vertices, joint_rotvecs, image_texture, camera_centers,
                precision: str = "fp32", compact: bool = False, correctives: bool | None = None,
                decode=None) -> DvaOutput:
        """``precision`` ("fp32", "bf16", "fp16"): the encoders and decoders run under autocast in that
        type; the geometry stays fp32 and the outputs are fp32. ``compact``: the decoders write the
        payload in one pass (:meth:`~uvatar.dva.decoders.DvaDecoder.payload`, the same values and
        gradients with S times smaller colour slabs; what training uses) where the colour skip is off;
        the default is the reference path (:meth:`~uvatar.dva.decoders.DvaDecoder.forward`).
        ``correctives``: whether the motion correctives apply, when the caller knows it on the host (a
        trainer's step count); None reads the ``correctives_on`` buffer (a read-back on a GPU).
        ``decode``: the compact path's encoders and decoders, an :class:`EncodeDecode` of this model
        (compiled, say) in ``precision``; None makes one per call."""
        pose_maps, f_view, skip = self.inputs(posed_vertices, joint_rotvecs, image_texture, camera_centers)
        dtype = PRECISIONS[precision]
        compact = compact and skip is None  # with the colour skip, the decoder's own colour differs from the payload's
        if compact:
            decode = EncodeDecode(self, dtype) if decode is None else decode
            motion, payload = decode(pose_maps, image_texture, f_view)
            learned = payload[:, :, :3]
        else:
            with torch.autocast(posed_vertices.device.type, dtype=dtype, enabled=dtype != torch.float32):
                decoded = self.decoder(self.pose_encoder(pose_maps), self.image_encoder(image_texture), f_view, skip)
            motion, rgb, density, learned = (t.float() for t in decoded)
            payload = torch.cat([rgb, density], 2)
        on = bool(self.correctives_on) if correctives is None else bool(correctives)
        pos, rot, scl = self.place(posed_vertices, motion, on)
        return DvaOutput(pos, rot, scl, payload, motion, learned)

    def inputs(self, posed_vertices, joint_rotvecs, image_texture, camera_centers):
        """What the encoders and decoders take besides the image texture, all fp32: the masked pose
        maps (B, 3 Jc, W, W), the view features (B, 1, W, W) and the colour skip ((colour, weight) at the
        voxel columns, or None)."""
        pose_maps = pose_feature_maps(joint_rotvecs, self.texel_weights, self.joint_index)
        f_view = self.view_features(posed_vertices, camera_centers)
        skip = texture_at_voxels(image_texture, self.voxel_uv) if self.cfg.features.colour_skip else None
        return pose_maps, f_view, skip

    def view_features(self, posed_vertices, camera_centers):
        """(B, 1, W, W) view feature map (:func:`~uvatar.dva.features.view_feature_map`)."""
        return view_feature_map(self.grid.raster, self.template, posed_vertices, camera_centers)

    def place(self, posed_vertices, motion, correctives: bool):
        """Primitive positions (B, K, 3), rotations (B, K, 3, 3), scales (B, K, 3) of the posed body,
        with the decoded ``motion`` (B, 9, W, W) correctives applied when ``correctives``."""
        pos, rot = articulated_frames(self.grid, self.template, posed_vertices)
        return apply_correctives(pos, rot, self.rest_scales, motion, self.cfg.primitives, correctives)

    def render_rays(self, out: DvaOutput, b: int, origins, directions, background=None, camera=None,
                    pixels=None, budget=None):
        """Render rays (N, 3) through sample ``b``: rgb (N, 3) (composited over ``background`` (3,) if
        given), alpha (N,). With ``camera`` and integer ``pixels`` (N, 2) (the rays' pixels in that
        camera) culling uses projected rectangles (faster, same result); ``budget``: the Warp marcher's
        fixed pair buffer (:class:`~uvatar.dva.raymarch_warp.PairBudget`: no read-back)."""
        rgb, alpha = raymarch(origins, directions, out.primitives(b), self.cfg.raymarch, camera=camera,
                              pixels=pixels, budget=budget)
        if background is not None:
            rgb = rgb + (1.0 - alpha)[:, None] * background
        return rgb, alpha


def pixel_rays(camera, pixels: np.ndarray, device="cpu", dtype=torch.float32):
    """World rays through pixel centres. pixels (N, 2) integer (x, y) -> origins, directions (N, 3)
    as tensors; lens distortion removed as everywhere else (:func:`uvatar.render.cameras.camera_rays`)."""
    from uvatar.devices import to_device_async
    from uvatar.render.cameras import camera_rays

    o, d = camera_rays(camera, np.asarray(pixels, np.float64).reshape(-1, 2))
    return to_device_async(o, device, dtype), to_device_async(d, device, dtype)  # no stream sync on a GPU
