"""Animate an exported avatar with a motion: ``uvatar animate AVATAR --motion FILE -o video.mp4``.

Per pose (paper §3.5): generator (onnxruntime) -> texture + displacement; body posed, subdivided
twice, displaced (not on fingers/toes), textured; rendered by the Embree mesh renderer with any
camera; written to MP4, optionally one OBJ/GLB per frame. See :class:`AvatarRuntime`.

Cameras (``AnimateConfig.camera``): "orbit" (default: one turn around the body over the clip),
"front", "back", "left", "right" (the body's left, +X) — these follow the body's centre — or a folder
with EasyMocap intri.yml/extri.yml (``camera_name`` picks one; default the first).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uvatar.avh.poses import PoseSequence, load_pose_sequence
from uvatar.avh.runtime import AvatarRuntime
from uvatar.errors import InputError, check_values

log = logging.getLogger(__name__)

VIEW_AZIMUTH = {"front": 0.0, "left": 90.0, "back": 180.0, "right": 270.0}


RENDER_BYTES_PER_PIXEL = 96  # rasterizer buffers of one frame (depth, barycentrics, face ids, colour), float32


MESH_FORMATS = ("obj", "glb", "gltf", "fbx", "uvol", "vols", "abc", "usd", "usdz")   # what --obj-dir writes: a mesh a frame, or a take
VOLS_MAX_LEVELS = 1   # anny subdivided once: 57,205 vertices once split along its UV seams, under uint16's 65,536


@dataclass(frozen=True)
class AnimateConfig:
    """size: image side in pixels; camera: see module docstring; orbit_degrees: turn over the clip;
    fov_deg: vertical field of view; elevation_deg: camera height angle; max_frames / stride: motion
    subsampling; levels / scheme: subdivision; shading: Lambert headlight on top of the texture;
    fps: None = the motion's; mesh_format: "obj", "glb", "gltf" (one JSON file) or "fbx" (binary
    7.4, texture embedded) for per-frame meshes, "uvol" for the frames as a UVOL 2 take (Draco meshes,
    KTX2 textures, the player's manifest: the Universal Volumetric player streams it), "vols" as a
    Volograms 1.3 take (one ``avatar.vols``: a keyframe, then tracked frames, a Basis ETC1S texture
    each; Volograms' players read it), "abc" as an Alembic mesh cache
    (``avatar.abc`` + ``textures/avatar_<frame>.png``: Maya, Houdini, Blender, Unreal read it), "usd" /
    "usdz" as a USD stage (``avatar.usdc`` + ``textures/``, or one ``avatar.usdz``: the points and the
    material's texture file time-sampled; usdview, Omniverse, Blender read it)."""

    size: int = 512
    camera: str = "orbit"
    camera_name: str | None = None
    orbit_degrees: float = 360.0
    fov_deg: float = 30.0
    elevation_deg: float = 10.0
    max_frames: int | None = None
    stride: int = 1
    levels: int = 2
    scheme: str = "midpoint"
    shading: bool = False
    background: float = 1.0
    fps: float | None = None
    mesh_format: str = "obj"
    progress: bool = True

    def __post_init__(self) -> None:
        checks = [(self.size >= 16, f"size must be at least 16 pixels, got {self.size}"),
                  (self.max_frames is None or self.max_frames >= 1, f"frames must be at least 1, got {self.max_frames}"),
                  (self.stride >= 1, f"stride must be at least 1, got {self.stride}"),
                  (self.levels >= 0, f"subdivision levels must be >= 0, got {self.levels}"),
                  (self.fps is None or self.fps > 0, f"fps must be > 0, got {self.fps}"),
                  (0 < self.fov_deg < 180, f"fov must be in (0, 180) degrees, got {self.fov_deg}"),
                  (self.mesh_format in MESH_FORMATS, f"mesh format must be one of {', '.join(MESH_FORMATS)}, got "
                                                     f"{self.mesh_format!r}"),
                  (self.mesh_format != "vols" or self.levels <= VOLS_MAX_LEVELS,
                   f"a Volograms take (mesh format vols) holds at most 65,536 vertices a frame (its players draw "
                   f"uint16 indices): {self.levels} subdivision levels make ~224,000 on anny; levels 1 makes "
                   f"~57,000, levels 0 ~15,000")]
        check_values(checks)


def frame_camera(config: AnimateConfig, t: int, count: int, vertices: np.ndarray, distance: float,
                 fixed_cameras: dict | None = None):
    """The camera for frame ``t`` of ``count`` looking at ``vertices`` (V, 3) from ``distance`` metres."""
    from uvatar.render import look_at_camera

    if fixed_cameras:
        name = config.camera_name or sorted(fixed_cameras)[0]
        if name not in fixed_cameras:
            raise InputError(config.camera, f"no camera named {name!r} (has {sorted(fixed_cameras)})")
        return fixed_cameras[name]
    if config.camera == "orbit":
        az = config.orbit_degrees * t / max(count, 1)
    elif config.camera in VIEW_AZIMUTH:
        az = VIEW_AZIMUTH[config.camera]
    else:
        raise InputError(config.camera, "unknown camera: orbit, front, back, left, right or a cameras folder")
    target = 0.5 * (vertices.min(0) + vertices.max(0))
    el, a = np.radians(config.elevation_deg), np.radians(az)
    eye = target + distance * np.array([np.cos(el) * np.sin(a), np.sin(el), np.cos(el) * np.cos(a)])
    return look_at_camera(eye, target, (0, 1, 0), config.fov_deg, config.size, config.size, f"{config.camera}_{t}")


def framing_distance(vertices: np.ndarray, fov_deg: float, margin: float = 1.1) -> float:
    """Distance (m) at which a sphere of the largest bounding-box side of ``vertices`` (V, 3) fills the
    field of view (times ``margin``); any view direction then keeps the body in a square image."""
    radius = 0.5 * float((vertices.max(0) - vertices.min(0)).max())
    return margin * radius / np.sin(np.radians(fov_deg) / 2)


def _load_cameras(config: AnimateConfig) -> dict | None:
    if config.camera in VIEW_AZIMUTH or config.camera == "orbit":
        return None
    folder = Path(config.camera)
    if not (folder / "intri.yml").is_file():
        raise InputError(folder, "unknown camera: orbit, front, back, left, right or a folder with intri.yml")
    from uvatar.capture import read_cameras

    return read_cameras(folder)


def _textured(mesh):
    from uvatar.capture import TexturedMesh

    return TexturedMesh(mesh.vertices, mesh.faces, mesh.uvs, mesh.uv_faces, mesh.texture)


def write_frame_mesh(path: Path, mesh) -> None:
    from uvatar.capture import write_mesh

    write_mesh(path, _textured(mesh))


def render_sequence(runtime: AvatarRuntime, motion: PoseSequence, config: AnimateConfig,
                    mesh_dir: str | Path | None = None) -> list[np.ndarray]:
    """Render every pose of ``motion``; returns (size, size, 3) float32 frames. Non-finite poses are skipped."""
    from tqdm import tqdm

    from uvatar.render import render_mesh

    finite = np.isfinite(motion.poses).all(1) & np.isfinite(motion.Rh).all(1) & np.isfinite(motion.Th).all(1)
    if not finite.all():
        log.warning("skipping %d frames with non-finite poses", int((~finite).sum()))
    idx = np.flatnonzero(finite)
    if len(idx) == 0:
        raise InputError("motion", "no frame with a finite pose")
    cameras = _load_cameras(config)
    frames: list[np.ndarray] = []
    distance = None
    meshes = runtime.meshes(motion.poses[idx], motion.Rh[idx], motion.Th[idx], motion.scale[idx])
    take = None
    if mesh_dir is not None and config.mesh_format == "uvol":
        from uvatar.capture.uvol_take import UvolTakeWriter

        take = UvolTakeWriter(mesh_dir, fps=config.fps or motion.fps)
    elif mesh_dir is not None and config.mesh_format == "vols":
        from uvatar.capture.vols_take import VolsTakeWriter

        take = VolsTakeWriter(Path(mesh_dir) / "avatar.vols", fps=config.fps or motion.fps)
    elif mesh_dir is not None and config.mesh_format == "abc":
        from uvatar.capture.abc_take import AlembicTakeWriter

        take = AlembicTakeWriter(Path(mesh_dir) / "avatar.abc", fps=config.fps or motion.fps)
    elif mesh_dir is not None and config.mesh_format in ("usd", "usdz"):
        from uvatar.capture.usd_take import UsdTakeWriter

        suffix = ".usdz" if config.mesh_format == "usdz" else ".usdc"
        take = UsdTakeWriter(Path(mesh_dir) / f"avatar{suffix}", fps=config.fps or motion.fps)
    for t, mesh in enumerate(tqdm(meshes, total=len(idx), desc="animate", disable=not config.progress)):
        if distance is None:
            distance = framing_distance(mesh.vertices, config.fov_deg)
        cam = frame_camera(config, t, len(idx), mesh.vertices, distance, cameras)
        result = render_mesh(mesh.vertices, mesh.faces, cam, mesh.uvs, mesh.uv_faces, mesh.texture,
                             background=config.background, shading=config.shading)
        frames.append(result.rgb)
        if take is not None:
            take.add(_textured(mesh))
        elif mesh_dir is not None:
            name = motion.names[idx[t]] if motion.names else f"{t:06d}"
            write_frame_mesh(Path(mesh_dir) / f"{name}.{config.mesh_format}", mesh)
    if take is not None:
        take.close()
    return frames


def animate(avatar_dir: str | Path, motion: str | Path | PoseSequence, output: str | Path,
            config: AnimateConfig = AnimateConfig(), mesh_dir: str | Path | None = None, body=None,
            device: str = "cpu") -> Path:
    """Render ``motion`` (a spec for :func:`load_pose_sequence` or a PoseSequence) to ``output`` (MP4).

    Returns the path written (a GIF beside it if MP4 encoding is unavailable).
    """
    from uvatar.render import write_video
    from uvatar.render.video import check_video_path
    from uvatar.resources import check_memory

    if config.mesh_format not in MESH_FORMATS:
        raise InputError(config.mesh_format, f"mesh format must be one of {', '.join(MESH_FORMATS)}")
    check_video_path(output)
    check_memory(RENDER_BYTES_PER_PIXEL * config.size ** 2, "size", f"rendering {config.size}² pixels")
    runtime = AvatarRuntime(avatar_dir, body=body, device=device, levels=config.levels, scheme=config.scheme)
    seq = motion if isinstance(motion, PoseSequence) else load_pose_sequence(motion, runtime.body, runtime.shape)
    seq = seq.subsample(config.max_frames, config.stride)
    if seq.on_floor:  # a retarget put the body's soles on the floor: put the avatar's surface there
        seq.Th = seq.Th - np.array([0.0, runtime.sole_offset(), 0.0], np.float32)
    check_memory((RENDER_BYTES_PER_PIXEL + 3 * len(seq)) * config.size ** 2, "size",
                 f"{len(seq)} frames of {config.size}² pixels")
    frames = render_sequence(runtime, seq, config, mesh_dir)
    return Path(write_video(output, frames, fps=config.fps or seq.fps))
