"""AVH generator: body pose -> (texture, displacement) maps in the body's UV layout (AVH paper §3.3).

Architecture (per sample)::

    pose angles (3·J_c,) radians  --(sin, cos)-->  (6·J_c,)
      --Linear(6·J_c, 256)-ReLU-Linear(256, latent)-->  latent pose z (latent,)
    cuboid = learned feature maps (latent, f_c, f_c) * z[:, None, None]      # z selects/modulates maps
    two decoders (texture, displacement), same cuboid, separate weights; each is
      n = log2(R / f_c) levels of
         2×2 stride-2 transposed conv halving the channels  (C -> C/2, resolution ×2)
         double 3×3 conv + BatchNorm + ReLU                   (C/2 -> C/2 -> C/2)
      then a 1×1 conv -> 3 channels.
    texture      = (tanh(x) + 1) / 2            in [0, 1]
    displacement = tanh(x) · displacement_scale  metres (default ±5 cm)

Placing the transposed conv at the start of each level (the paper's sequence "double conv, then
up-conv" with the up-conv leading) gives, per decoder, 2·C² + 18·(C/2)² = 6.5·C² weights at the first
level and ≈ 6.5·4/3 = 8.67·latent² over all levels, which reproduces every Table 1 parameter count to
within ~1 % (e.g. (32, 1024): 32²·1024 + 2·8.67·1024² + MLP ≈ 19.5 M).

Texel conditioning (``conditioning="texel"``, beyond the paper; :mod:`uvatar.avh.texel_pose`): the
same raw angles also make a UV map of the skinning-weighted rotations of the joints that skin each
texel (B, 6, R, R); each decoder adds a 1×1 projection of it (average-pooled to the level's
resolution) to its features at the cuboid and after every transposed conv. The projections start at
zero, so training starts from the global model and learns how much local pose to use.

Studio orientation (``orientation="studio"``, beyond the paper): the body's orientation in the
capture's world (``Rh``) is one more conditioning "joint" (the root, last in ``pose_angles``). A
studio's lights are fixed in its world, so what it bakes into every frame depends on which way the
body faces them. The global MLP sees it like any angle; with texel conditioning the texel map also
carries each texel's posed normal in that world, and a **shading head** (per-texel 1×1 convs over the
texel map, last layer zero at start) multiplies the texture by ``exp(s)``: texture = albedo-like
decoder output × shading, the way the light entered the capture. Without it (``"body"``, the paper)
the generator cannot tell a body lit from the front from one lit from behind. ``shading_lights`` adds a
learned light rig to the shading head (:mod:`uvatar.avh.lights`: per-texel ambient + learned lights ×
max(0, n·l)), ``shading_shadows`` / ``shading_occlusion`` the posed limbs' cast shadows and occlusion
for it (:mod:`uvatar.avh.shadows`).

Maps are BCHW float32; image row 0 is v = 1 (UV v up), the layout of the baked maps. Only
ONNX-portable ops are used (Linear, Mul, ConvTranspose, Conv, BatchNorm, Relu, Tanh, Sin, Cos;
texel conditioning adds Sqrt, MatMul, AveragePool; the shading head Exp and Clip; the shadows Sigmoid,
ReduceProd and Resize).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import torch
from torch import nn

from uvatar.avh.lights import LightRig
from uvatar.avh.shadows import BodyShadows
from uvatar.avh.texel_pose import TexelPoseMap, input_statistics, pooled, standardize

#: Most lights of the light-rig shading head (each is a learned direction and colour; a rig of a few
#: already spans a studio's lighting, and the head's cost grows with every light).
MAX_SHADING_LIGHTS = 64

#: Pose conditioning of the decoders: the paper's global latent only, or also a texel-aligned pose map.
CONDITIONINGS = ("global", "texel")
#: What the pose input holds: the local pose only (the paper), or also the body's orientation in the studio.
ORIENTATIONS = ("body", "studio")

#: Paper Table 1 parameter counts, keyed by preset name.
PAPER_PARAMETER_COUNTS: dict[str, int] = {
    "fc16-l512": 4_800_000,
    "fc16-l2048": 73_800_000,
    "fc32-l1024": 19_500_000,
    "fc64-l128": 877_000,
    "fc64-l512": 6_800_000,
    "fc128-l256": 5_400_000,
}


@dataclass(frozen=True)
class AvhConfig:
    """Size of the AVH generator.

    feature_size: f_c, side of the learned feature cuboid (texels); resolution / f_c must be 2^n.
    latent: latent pose size = channels of the cuboid.
    resolution: output texel resolution R (maps are R×R).
    num_pose_joints: J_c, number of conditioning joints (input is 3·J_c angles; 23 for SMPL).
    hidden: hidden units of the pose MLP (paper: 256).
    displacement_scale: metres; displacement = tanh(·) × scale.
    displacement_residual_scale: metres of displacement per unit of the displacement decoder's output
        (before its output bias and the tanh; where the tanh is near linear): the decoder's output is
        multiplied by ``displacement_residual_scale / displacement_scale``. 0: by 1 (the paper's). The
        pose-dependent residual of a garment is millimetres, 1/20 of the ±5 cm range, so at gain 1
        every optimizer step of the last layer moves it by about the size of the signal.
    min_channels: floor on decoder channels at deep levels.
    output_bias: add a learned per-texel bias map (3, R, R) to each decoder's output (before the
        activation), initialized from the training data's mean maps by :func:`init_output_bias`; the
        network then learns the pose-dependent residual. Off for the paper's Table 1 presets (their
        parameter counts are the paper's), on for the CPU presets, whose short trainings would
        otherwise spend most steps learning the static texture detail.
    conditioning: "global" (the paper: the pose reaches the decoders only through the cuboid) or
        "texel" (also a UV map of the skinning-weighted rotations of the joints that skin each texel,
        fed to every decoder level; :mod:`uvatar.avh.texel_pose`).
    orientation: "body" (the paper: local joint angles only) or "studio" (the last conditioning
        joint is the root and carries the body's orientation Rh in the capture's world; with texel
        conditioning also the texel's world normal and the shading head).
    shading_hidden: channels of the shading head's two hidden 1×1 convs (texel + studio only).
    shading_lights: learned lights of the light-rig head (texel + studio only; 0: none, the MLP shading
        head alone): texture × (per-texel ambient + Σ per-texel share · max(0, n·v_k)), :mod:`uvatar.avh.lights`.
    shading_shadows: with the light rig, each light is also blocked by the posed limbs (soft cast
        shadows of spheres along the skeleton, :mod:`uvatar.avh.shadows`).
    shading_occlusion: with the shadows, the rig's ambient is also dimmed by the limbs' occlusion (each
        sphere's cosine-weighted solid angle seen from the texel).
    pose_normalization: standardize the pose inputs by the training frames' statistics (beyond the
        paper): the encoded pose of the MLP and, with texel conditioning, each joint's rot6d before it is
        blended into the texel map, as (x - mean) / max(std, pose_scale_floor), clipped to ±pose_clip.
        A take whose person stands and talks moves its joints by about 1° (sin/cos inputs vary by
        ~0.005), so without it the pose-dependent part of the maps starts ~100x weaker than the mean
        and short trainings never leave the mean maps. The clip bounds what a pose far outside the
        training range can do (the generator's response saturates at ±pose_clip standard deviations).
        Statistics: :meth:`AvhGenerator.set_pose_statistics` (buffers saved with the weights and
        exported in the ONNX graph).
    pose_scale_floor: smallest std (sin/cos units, ~radians) a pose input is divided by.
    pose_clip: standardized pose inputs are clipped to ±this.
    """

    feature_size: int = 32
    latent: int = 1024
    resolution: int = 1024
    num_pose_joints: int = 23
    hidden: int = 256
    displacement_scale: float = 0.05
    displacement_residual_scale: float = 0.0
    min_channels: int = 8
    output_bias: bool = False
    conditioning: str = "global"
    orientation: str = "body"
    shading_hidden: int = 16
    shading_lights: int = 0
    shading_shadows: bool = False
    shading_occlusion: bool = False
    pose_normalization: bool = False
    pose_scale_floor: float = 0.02
    pose_clip: float = 4.0

    def __post_init__(self):
        ratio = self.resolution / self.feature_size
        if self.feature_size < 1 or self.resolution < self.feature_size or ratio != 2 ** round(math.log2(ratio)):
            raise ValueError(f"resolution {self.resolution} must be feature_size {self.feature_size} "
                             f"times a power of two")
        if not 0 <= self.shading_lights <= MAX_SHADING_LIGHTS:
            raise ValueError(f"shading_lights must be in [0, {MAX_SHADING_LIGHTS}], got {self.shading_lights}")
        if self.shading_shadows and not self.shading_lights:
            raise ValueError("shading_shadows needs shading_lights >= 1 (the lights that cast them)")
        if self.shading_occlusion and not self.shading_shadows:
            raise ValueError("shading_occlusion needs shading_shadows (the limbs that occlude)")
        if not 0.0 <= self.displacement_residual_scale <= self.displacement_scale:
            raise ValueError(f"displacement_residual_scale must be in [0, displacement_scale "
                             f"{self.displacement_scale}], got {self.displacement_residual_scale}")
        if self.pose_scale_floor <= 0 or self.pose_clip <= 0:
            raise ValueError(f"pose_scale_floor and pose_clip must be positive, got {self.pose_scale_floor}, "
                             f"{self.pose_clip}")
        if self.latent < 1 or self.num_pose_joints < 1 or self.hidden < 1:
            raise ValueError("latent, num_pose_joints and hidden must be positive")
        if self.conditioning not in CONDITIONINGS:
            raise ValueError(f"conditioning must be one of {', '.join(CONDITIONINGS)}, got {self.conditioning!r}")
        if self.orientation not in ORIENTATIONS:
            raise ValueError(f"orientation must be one of {', '.join(ORIENTATIONS)}, got {self.orientation!r}")

    def check_lights_used(self) -> None:
        """Raise ValueError when lights are asked for that this generator would ignore (a light rig
        without the shading head, which only texel conditioning with the studio orientation has). A
        check for a new training run: a run saved before it was made loads as it is."""
        if self.shading_lights and not self.shading:
            raise ValueError(f"shading_lights={self.shading_lights} adds lights to the shading head, which only "
                             f"conditioning='texel' with orientation='studio' has (this run: "
                             f"conditioning={self.conditioning!r}, orientation={self.orientation!r})")

    @property
    def shading(self) -> bool:
        """Whether the generator has the shading head (texel conditioning with the studio orientation)."""
        return self.conditioning == "texel" and self.orientation == "studio"

    @property
    def texel_channels(self) -> int:
        """Channels of the texel pose map (0 without texel conditioning)."""
        if self.conditioning != "texel":
            return 0
        return 9 if self.orientation == "studio" else 6

    @property
    def num_levels(self) -> int:
        return round(math.log2(self.resolution / self.feature_size))

    @property
    def pose_input_size(self) -> int:
        """Size of the encoded pose: (sin, cos) of each of the 3·J_c angles."""
        return 6 * self.num_pose_joints

    def level_resolutions(self) -> list[int]:
        """Side of the decoder features at the cuboid and after each level (f_c, 2 f_c, ..., R)."""
        return [self.feature_size << k for k in range(self.num_levels + 1)]

    def level_channels(self) -> list[int]:
        """Channels after each level's transposed conv (C_k = max(latent / 2^k, min_channels))."""
        return [max(self.latent >> k, self.min_channels) for k in range(1, self.num_levels + 1)]

    def to_dict(self) -> dict:
        return asdict(self)


#: Named sizes. Table 1 rows at the paper's 1024² output with SMPL's 23 joints, plus small CPU sizes.
PRESETS: dict[str, AvhConfig] = {
    "fc16-l512": AvhConfig(16, 512),
    "fc16-l2048": AvhConfig(16, 2048),
    "fc32-l1024": AvhConfig(32, 1024),
    "fc64-l128": AvhConfig(64, 128),
    "fc64-l512": AvhConfig(64, 512),
    "fc128-l256": AvhConfig(128, 256),
    "cpu-tiny": AvhConfig(8, 64, resolution=64, output_bias=True),
    "cpu-small": AvhConfig(16, 128, resolution=128, output_bias=True),
    "cpu-medium": AvhConfig(16, 256, resolution=256, output_bias=True),
    # 256² maps at about cpu-small's cost: the per-texel bias carries the static detail at full resolution,
    # the narrow decoder (64 -> 8 channels) the pose-dependent residual
    "cpu-256": AvhConfig(16, 64, resolution=256, output_bias=True),
}


def preset(name: str, **overrides) -> AvhConfig:
    """Return the preset ``name`` with fields replaced by ``overrides`` (e.g. resolution, num_pose_joints)."""
    if name not in PRESETS:
        raise KeyError(f"unknown AVH preset {name!r}; choose from {', '.join(PRESETS)}")
    return replace(PRESETS[name], **overrides)


def encode_pose(angles: torch.Tensor) -> torch.Tensor:
    """(…, N) angles in radians -> (…, 2N) as [sin(a_0), cos(a_0), sin(a_1), cos(a_1), …]."""
    return torch.stack([torch.sin(angles), torch.cos(angles)], dim=-1).flatten(-2)


def select_conditioning_angles(poses: torch.Tensor, conditioning_joints) -> torch.Tensor:
    """(…, J·3) local axis-angle poses -> (…, 3·J_c) angles of the conditioning joints, in their order."""
    idx = torch.as_tensor(list(conditioning_joints), dtype=torch.long, device=poses.device)
    return poses.reshape(*poses.shape[:-1], -1, 3).index_select(-2, idx).flatten(-2)


def root_joint(joint_parents) -> int:
    """Index of the body's root joint (the one without a parent)."""
    roots = [j for j, q in enumerate(joint_parents) if int(q) < 0]
    if len(roots) != 1:
        raise ValueError(f"the skeleton must have one root joint, found {len(roots)}")
    return roots[0]


def with_orientation(poses, Rh, root: int):
    """(…, J·3) root-zero local poses and (…, 3) Rh -> a copy with the root slot holding Rh: the pose
    input of an ``orientation="studio"`` generator (numpy or torch, whichever ``poses`` is)."""
    if isinstance(poses, torch.Tensor):
        out = poses.clone()
        out[..., 3 * root:3 * root + 3] = torch.as_tensor(Rh, dtype=poses.dtype, device=poses.device)
        return out
    import numpy as np

    out = np.array(poses, dtype=np.float32, copy=True)
    out[..., 3 * root:3 * root + 3] = np.asarray(Rh, np.float32)
    return out


def double_conv(channels: int) -> nn.Sequential:
    """(conv3×3 -> BatchNorm -> ReLU) × 2, channels preserved."""
    layers = []
    for _ in range(2):
        layers += [nn.Conv2d(channels, channels, 3, padding=1, bias=False), nn.BatchNorm2d(channels),
                   nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


class MapDecoder(nn.Module):
    """Feature cuboid (B, latent, f_c, f_c) -> raw 3-channel map (B, 3, R, R) (before the output activation).

    With texel conditioning, ``pose_proj[k]`` (1×1 conv, zero at start) adds the texel pose map
    pooled to the level's resolution: at the cuboid (k = 0) and after the k-th transposed conv."""

    def __init__(self, config: AvhConfig, gain: float = 1.0):
        super().__init__()
        self.gain = float(gain)  # the network's output is multiplied by it before the bias
        layers: list[nn.Module] = []
        c_in = config.latent
        for c_out in config.level_channels():
            layers.append(nn.ConvTranspose2d(c_in, c_out, kernel_size=2, stride=2))
            layers.append(double_conv(c_out))
            c_in = c_out
        if not layers:  # resolution == feature_size
            layers.append(double_conv(c_in))
        layers.append(nn.Conv2d(c_in, 3, kernel_size=1))
        self.net = nn.Sequential(*layers)
        R = config.resolution
        self.bias = nn.Parameter(torch.zeros(1, 3, R, R)) if config.output_bias else None
        self.pose_proj = None
        if config.conditioning == "texel":
            self.pose_proj = nn.ModuleList(nn.Conv2d(config.texel_channels, c, 1)
                                           for c in [config.latent, *config.level_channels()])
            for conv in self.pose_proj:
                nn.init.zeros_(conv.weight)
                nn.init.zeros_(conv.bias)
            self.level_resolutions = config.level_resolutions()

    def forward(self, cuboid: torch.Tensor, pose_map: torch.Tensor | None = None) -> torch.Tensor:
        if self.pose_proj is None:
            out = self.net(cuboid)
        else:
            x = cuboid + self.pose_proj[0](pooled(pose_map, self.level_resolutions[0]))
            k = 1
            for layer in self.net:
                x = layer(x)
                if isinstance(layer, nn.ConvTranspose2d):
                    x = x + self.pose_proj[k](pooled(pose_map, self.level_resolutions[k]))
                    k += 1
            out = x
        if self.gain != 1.0:
            out = out * self.gain
        return out if self.bias is None else out + self.bias


def shading_head(config: AvhConfig) -> nn.Sequential:
    """Texel pose map (B, 9, R, R) -> log shading (B, 1, R, R): per-texel 1×1 convs (the same function
    of a texel's world normal and local pose everywhere), the last layer zero so training starts unlit."""
    h = config.shading_hidden
    head = nn.Sequential(nn.Conv2d(config.texel_channels, h, 1), nn.ReLU(inplace=True), nn.Conv2d(h, h, 1),
                         nn.ReLU(inplace=True), nn.Conv2d(h, 1, 1))
    nn.init.zeros_(head[-1].weight)
    nn.init.zeros_(head[-1].bias)
    return head


class AvhGenerator(nn.Module):
    """Encoded pose (B, 6·J_c) -> texture (B, 3, R, R) in [0, 1], displacement (B, 3, R, R) metres.

    Texel conditioning also needs the raw angles (B, 3·J_c) (``pose_angles``) and the texel skinning
    weights in ``texel_pose`` (:meth:`TexelPoseMap.set_weights`; saved in the state dict)."""

    def __init__(self, config: AvhConfig):
        super().__init__()
        self.config = config
        self.pose_mlp = nn.Sequential(
            nn.Linear(config.pose_input_size, config.hidden), nn.ReLU(inplace=True),
            nn.Linear(config.hidden, config.latent),
        )
        f = config.feature_size
        self.feature_maps = nn.Parameter(torch.randn(config.latent, f, f) * 0.5)
        self.texture_decoder = MapDecoder(config)
        residual = config.displacement_residual_scale
        self.displacement_decoder = MapDecoder(config, residual / config.displacement_scale if residual else 1.0)
        self.texel_pose = (TexelPoseMap(config.num_pose_joints, config.resolution,
                                        world_normals=config.orientation == "studio",
                                        normalization=(config.pose_scale_floor, config.pose_clip)
                                        if config.pose_normalization else None)
                           if config.conditioning == "texel" else None)
        if config.pose_normalization:  # identity until set_pose_statistics
            self.register_buffer("pose_code_mean", torch.zeros(config.pose_input_size))
            self.register_buffer("pose_code_scale", torch.ones(config.pose_input_size))
        self.shading = shading_head(config) if config.shading else None
        self.lights = (LightRig(config.shading_lights, config.resolution)
                       if config.shading and config.shading_lights else None)
        self.shadows = (BodyShadows(config.num_pose_joints, config.resolution)
                        if self.lights is not None and config.shading_shadows else None)

    def set_pose_statistics(self, pose_angles: torch.Tensor) -> None:
        """Standardize the pose inputs by these training frames' (N, 3·J_c) conditioning angles
        (radians): mean and std (floored at ``pose_scale_floor``) of the encoded pose and, with texel
        conditioning, of each joint's rot6d. Needs ``pose_normalization``."""
        if not self.config.pose_normalization:
            raise ValueError("set_pose_statistics needs AvhConfig.pose_normalization")
        a = torch.as_tensor(pose_angles, dtype=torch.float32).to(self.pose_code_mean.device)
        mean, scale = input_statistics(encode_pose(a), self.config.pose_scale_floor)
        with torch.no_grad():
            self.pose_code_mean.copy_(mean)
            self.pose_code_scale.copy_(scale)
        if self.texel_pose is not None:
            self.texel_pose.set_statistics(a)

    def cuboid(self, pose_encoded: torch.Tensor) -> torch.Tensor:
        """(B, 6·J_c) -> feature cuboid (B, latent, f_c, f_c)."""
        if self.config.pose_normalization:
            pose_encoded = standardize(pose_encoded, self.pose_code_mean, self.pose_code_scale, self.config.pose_clip)
        z = self.pose_mlp(pose_encoded)
        return self.feature_maps.unsqueeze(0) * z[:, :, None, None]

    def forward(self, pose_encoded: torch.Tensor,
                pose_angles: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        tracing = torch.jit.is_tracing() or torch.compiler.is_compiling()
        if not tracing and (pose_encoded.ndim != 2 or pose_encoded.shape[1] != self.config.pose_input_size):
            raise ValueError(f"pose_encoded must be (B, {self.config.pose_input_size}), "
                             f"got {tuple(pose_encoded.shape)}")
        pose_map = None
        if self.texel_pose is not None:
            if pose_angles is None:
                raise ValueError("texel conditioning needs pose_angles (B, 3·J_c) radians")
            pose_map = self.texel_pose(pose_angles)
        cub = self.cuboid(pose_encoded)
        texture = (torch.tanh(self.texture_decoder(cub, pose_map)) + 1.0) * 0.5
        if self.shading is not None:
            shade = torch.exp(self.shading(pose_map))
            if self.lights is not None:
                vis = None
                if self.shadows is not None:
                    world = self.texel_pose.world_rotations(pose_angles.reshape(pose_angles.shape[0], -1, 3))
                    vis = self.shadows(world, self.texel_pose.weights, self.lights.directions.reshape(-1, 3),
                                       pose_map[:, 6:9] if self.config.shading_occlusion else None)
                shade = shade * self.lights(pose_map[:, 6:9], vis)
            texture = torch.clamp(texture * shade, 0.0, 1.0)
        displacement = torch.tanh(self.displacement_decoder(cub, pose_map)) * self.config.displacement_scale
        return texture, displacement


class AvhFromAngles(nn.Module):
    """Wrapper taking raw conditioning-joint angles (B, 3·J_c) radians; encodes (sin, cos) inside.

    This is the graph exported to ONNX (input ``pose_angles``), so runtimes need no pre-processing.
    """

    def __init__(self, generator: AvhGenerator):
        super().__init__()
        self.generator = generator

    def forward(self, pose_angles: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.generator(encode_pose(pose_angles), pose_angles)


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


def expected_parameter_count(config: AvhConfig) -> int:
    """Closed-form parameter count of :class:`AvhGenerator` (no module is built; used for big presets)."""
    n = config.pose_input_size * config.hidden + config.hidden
    n += config.hidden * config.latent + config.latent
    n += config.latent * config.feature_size ** 2
    dec = 0
    c_in = config.latent
    for c in config.level_channels():
        dec += c_in * c * 4 + c  # transposed conv weight + bias
        dec += 2 * (9 * c * c + 2 * c)  # two bias-free 3x3 convs + BatchNorm affine
        c_in = c
    if not config.level_channels():
        dec += 2 * (9 * c_in * c_in + 2 * c_in)
    dec += 3 * c_in + 3
    if config.output_bias:
        dec += 3 * config.resolution ** 2
    if config.conditioning == "texel":
        dec += sum((config.texel_channels + 1) * c for c in [config.latent, *config.level_channels()])
    shading = 0
    if config.shading:
        h = config.shading_hidden
        shading = (config.texel_channels + 1) * h + (h + 1) * h + h + 1
        if config.shading_lights:
            shading += 3 * config.shading_lights + (1 + config.shading_lights) * config.resolution ** 2 + 1
            if config.shading_shadows:
                shading += 2 * config.num_pose_joints
    return n + 2 * dec + shading


def init_output_bias(model: AvhGenerator, texture_mean: torch.Tensor, displacement_mean: torch.Tensor) -> None:
    """Start an ``output_bias`` model at the given mean maps (3, R, R): biases = atanh of the targets,
    final 1×1 convs zeroed, so the first prediction is exactly the mean and training learns the
    pose-dependent residual. No-op without ``output_bias``."""
    if not model.config.output_bias:
        return
    with torch.no_grad():
        t = (2 * texture_mean.float() - 1).clamp(-0.98, 0.98)
        d = (displacement_mean.float() / model.config.displacement_scale).clamp(-0.98, 0.98)
        for dec, target in ((model.texture_decoder, t), (model.displacement_decoder, d)):
            dec.bias.copy_(torch.atanh(target)[None])
            final = dec.net[-1]
            final.weight.zero_()
            final.bias.zero_()


def format_count(n: int) -> str:
    """4_800_000 -> '4.8 M', 877_000 -> '877 K'."""
    if n >= 1_000_000:
        return f"{n / 1e6:.1f} M"
    if n >= 1_000:
        return f"{n / 1e3:.0f} K"
    return str(n)


def preset_table(num_pose_joints: int = 23) -> list[dict]:
    """One row per preset: name, f_c, latent, resolution, parameters, and the paper's count where it has one."""
    rows = []
    for name, cfg in PRESETS.items():
        cfg = replace(cfg, num_pose_joints=num_pose_joints)
        rows.append({"name": name, "feature_size": cfg.feature_size, "latent": cfg.latent,
                     "resolution": cfg.resolution, "parameters": expected_parameter_count(cfg),
                     "paper_parameters": PAPER_PARAMETER_COUNTS.get(name)})
    return rows
