"""A DVA telepresence frame, fast: pose + driving texture -> decoded primitives -> a camera's image.

The fast twin of :meth:`uvatar.dva.model.DvaModel.forward` + :func:`uvatar.dva.drive.render_camera`
(the reference: fp32, eager), for inference only. :class:`FrameConfig` selects the path:

* ``precision``: the encoders and decoders (every convolution) run under ``torch.autocast`` in bf16 or
  fp16; the geometry (texel positions and frames, view features, correctives) and the marcher stay
  fp32. The decoders write the marcher's payload in one pass (:meth:`~uvatar.dva.decoders.DvaDecoder.payload`):
  colour and shadow stay one layer per voxel column (not S) until that write, so no slab is larger
  than the payload the marcher reads.
* ``compile``: the encoders + decoders go through ``torch.compile`` (``compile_mode`` "reduce-overhead"
  adds CUDA graphs on a GPU); off by default (minutes of compilation on a small CPU).
* ``channels_last``: NHWC convolution inputs (what tensor cores prefer on a GPU).
* ``pairs_per_ray``: the Warp marcher's (ray, primitive) pair buffer holds this many pairs per ray of
  the camera (:class:`~uvatar.dva.raymarch_warp.PairBudget`), so its culling reads nothing back; 0: the
  exact buffer, sized from a read-back of the pair count every frame (the earlier behaviour).
* ``graph``: a driven frame (:meth:`FrameRenderer.drive`: unwrap, decode, place, march) is captured
  once in a CUDA graph and replayed (on CUDA with the Warp marcher; elsewhere the eager path runs).

No host sync inside a frame: the correctives switch is read once, at construction; what does not
change between frames (the camera's rays, pixel grid, matrices and centre, the driving rig's
matrices, the body's faces and its occlusion BVH, refitted per frame) is on the device from the first
frame on; the marcher's step count is bounded by ``RaymarchConfig.max_steps`` and its pair buffer by
``pairs_per_ray``. The first frame of a camera checks the buffer (one read-back) and grows it if it
overflowed; later frames look at it a frame late without blocking (:meth:`FrameRenderer.overflows`
counts the frames whose image lost pairs; the buffer grows after one). :meth:`FrameRenderer.check`
is the blocking check.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
import torch

from uvatar.dva.model import DvaOutput, EncodeDecode, pixel_rays
from uvatar.dva.raymarch import raymarch, resolve_marcher
from uvatar.precision import FastPathConfig

log = logging.getLogger(__name__)


def _no_mark(stage: str) -> None:
    """The default stage hook of :class:`FrameRenderer`: nothing."""


@dataclasses.dataclass(frozen=True)
class FrameConfig(FastPathConfig):
    """The fast frame's path (:class:`~uvatar.precision.FastPathConfig`): precision of the encoders
    and decoders, compile, compile_mode, channels_last; pairs_per_ray: the marcher's fixed pair buffer
    per ray (0: exact, read back per frame); graph: capture a driven frame in a CUDA graph."""

    pairs_per_ray: float = 16.0
    graph: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        from uvatar.errors import check_values

        check_values([(self.pairs_per_ray >= 0, f"pairs_per_ray must be >= 0, got {self.pairs_per_ray}"),
                      (not (self.graph and self.compile and self.compile_mode == "reduce-overhead"),
                       "graph=True captures the whole frame: compile_mode 'reduce-overhead' (graphs of its own) "
                       "cannot nest in it; use compile_mode 'default'")])


@dataclasses.dataclass
class _View:
    """What a camera's frames reuse, on the device: rays, their pixel grid, the camera centre."""

    camera: object
    origins: torch.Tensor
    directions: torch.Tensor
    pixels: torch.Tensor
    grid: object
    centre: torch.Tensor


class FrameRenderer:
    """Decode and render frames of a trained :class:`~uvatar.dva.model.DvaModel` the fast way.

    ``decode(posed_vertices (B, V, 3), joint_rotvecs (B, J, 3), image_texture (B, 4, R, R),
    camera_centers (B, 3)) -> DvaOutput`` (``learned_rgb`` is the payload's RGB);
    ``render(posed_vertices (V, 3), joint_rotvecs (J, 3), image_texture (4, R, R), camera, background)
    -> rgb (H, W, 3) in [0, 1], alpha (H, W)``, torch tensors on the model's device (nothing is copied
    back to the host). The model is used in place (eval mode; ``channels_last`` changes its parameters'
    memory layout, not their values). ``mark(stage)``, when given, is called as each stage of a frame
    ends ("unwrap", "inputs", "encode_decode", "place", "march"): what ``bench/dva_frame.py --profile``
    times (the eager path only: a replayed graph has no stages)."""

    def __init__(self, model, cfg: FrameConfig | None = None):
        from uvatar.dva.raymarch_warp import PairBudget

        self.model, self.cfg = model.eval(), cfg or FrameConfig()
        self.correctives = bool(model.correctives_on)
        self._decode = self.cfg.prepare(EncodeDecode(model, self.cfg.dtype, self.cfg.channels_last, not self.cfg.graph))
        self.device = model.texel_weights.device
        self._view: _View | None = None
        self._unwrap, self._backgrounds = {}, {}
        self.budget = PairBudget(1, self.device) if self.cfg.pairs_per_ray > 0 else None
        self._checked: set = set()  # camera sizes whose first frame checked the pair buffer
        self.overflows = 0  # frames found (a frame late) to have needed more pairs than the buffer held
        self._graph = None
        self.graph_error: str | None = None  # why a capture failed (frames then run eagerly)

    # ------------------------------------------------------------------------------------------ pieces
    @torch.no_grad()
    def decode(self, posed_vertices, joint_rotvecs, image_texture, camera_centers, mark=_no_mark) -> DvaOutput:
        m = self.model
        pose_maps, f_view, skip = m.inputs(posed_vertices, joint_rotvecs, image_texture, camera_centers)
        mark("inputs")
        motion, payload = self._decode(pose_maps, image_texture, f_view, *(skip or (None, None)))
        mark("encode_decode")
        pos, rot, scl = m.place(posed_vertices, motion, self.correctives)
        mark("place")
        return DvaOutput(pos, rot, scl, payload, motion, payload[:, :, :3])

    def view(self, camera) -> _View:
        """The device-side data of ``camera`` (rays (H*W, 3), pixels (H*W, 2), pixel grid, centre (1, 3));
        kept for the last camera. A new camera also sizes the pair buffer (``pairs_per_ray`` x H x W)."""
        if self._view is None or self._view.camera is not camera:
            from uvatar.devices import to_device_async
            from uvatar.dva.raymarch_cull import PixelGrid

            dev = self.device
            yy, xx = np.mgrid[:camera.height, :camera.width]
            pix = np.stack([xx.ravel(), yy.ravel()], 1)
            o, d = pixel_rays(camera, pix, "cpu")
            centre = torch.as_tensor(camera.center, dtype=torch.float32)[None]
            self._view = _View(camera, to_device_async(o, dev), to_device_async(d, dev), to_device_async(pix, dev),
                               PixelGrid.build(pix, dev), to_device_async(centre, dev))
            if self.budget is not None:
                self.budget.capacity = max(self.budget.capacity, math.ceil(self.cfg.pairs_per_ray * len(pix)))
        return self._view

    def rays(self, camera):
        """origins, directions (H*W, 3) and pixels (H*W, 2) of every pixel of ``camera``, on the model's
        device; kept for the last camera."""
        v = self.view(camera)
        return v.origins, v.directions, v.pixels

    def _background(self, background) -> torch.Tensor:
        key = tuple(float(v) for v in np.asarray(background, np.float32).reshape(-1))
        if key not in self._backgrounds:
            from uvatar.devices import to_device_async

            self._backgrounds[key] = to_device_async(np.asarray(key, np.float32), self.device)
        return self._backgrounds[key]

    def unwrapper(self, cameras):
        """The :class:`~uvatar.dva.unwrap_device.DeviceUnwrap` of a driving rig (kept per rig)."""
        key = tuple(id(c) for c in cameras)
        if key not in self._unwrap:
            from uvatar.dva.unwrap_device import DeviceUnwrap

            m = self.model
            self._unwrap[key] = (list(cameras), DeviceUnwrap(m.image_raster, m.template, cameras, self.device,
                                                             m.cfg.features.occlusion_eps))
        return self._unwrap[key][1]

    # ---------------------------------------------------------------------------------- pair buffer
    def check(self) -> int:
        """Blocking: the most pairs a frame needed since the last look (raises
        :class:`~uvatar.dva.raymarch_warp.PairOverflow` when the buffer was too small)."""
        return 0 if self.budget is None else self.budget.check()

    def _look(self, blocking: bool) -> bool:
        """Look at the pair count (a frame late unless ``blocking``); on an overflow count it, warn and
        grow the buffer (dropping a captured graph). True when it overflowed."""
        if self.budget is None:
            return False
        needed = self.budget.check(raise_error=False) if blocking else self.budget.poll()
        if not self.budget.overflowed(needed):
            return False
        if not blocking:
            self.overflows += 1
        new = math.ceil(needed * 1.25)
        log.warning("the marcher's pair buffer held %d pairs, a frame needed %d: %s; it now holds %d",
                    self.budget.capacity, needed, "re-rendering" if blocking else "that frame lost samples", new)
        self.budget.capacity = new
        self._graph = None
        return True

    # -------------------------------------------------------------------------------------- frames
    @torch.no_grad()
    def drive(self, posed_vertices, joint_rotvecs, cameras, images, masks, camera, background=(0.0, 0.0, 0.0),
              mark=_no_mark):
        """A telepresence frame: driving views (cameras, images (H, W, 3) and masks (H, W), torch on the
        device) + the frame's pose -> ``camera``'s rgb (H, W, 3), alpha (H, W). The views are unwrapped on
        the device (:class:`uvatar.dva.unwrap_device.DeviceUnwrap`, Warp), then :meth:`render`. With
        ``graph`` on CUDA the frame is a replay of a captured CUDA graph (captured on the first frame of a
        camera and rig, after two eager warm-up frames; a failed capture is logged, kept in ``graph_error``
        and the frames run eagerly)."""
        if self._graphable():
            return self._replay(posed_vertices, joint_rotvecs, cameras, images, masks, camera, background)
        return self._drive(posed_vertices, joint_rotvecs, cameras, images, masks, camera, background, mark)

    def _drive(self, posed_vertices, joint_rotvecs, cameras, images, masks, camera, background, mark=_no_mark,
               look: bool = True):
        tex = self.unwrapper(cameras).texture(posed_vertices, images, masks)
        mark("unwrap")
        return self._render(posed_vertices, joint_rotvecs, tex, camera, background, mark, look)

    @torch.no_grad()
    def render(self, posed_vertices, joint_rotvecs, image_texture, camera, background=(0.0, 0.0, 0.0),
               mark=_no_mark):
        return self._render(posed_vertices, joint_rotvecs, image_texture, camera, background, mark)

    def _render(self, posed_vertices, joint_rotvecs, image_texture, camera, background, mark=_no_mark,
                look: bool = True):
        view = self.view(camera)
        first = look and self.budget is not None and (camera.width, camera.height) not in self._checked
        out = self.decode(posed_vertices[None], joint_rotvecs[None], image_texture[None].to(self.device),
                          view.centre, mark)
        rgb, alpha = self._march(out, view, camera, mark)
        if first:  # the first frame of a camera size: a blocking look; marched again with a grown buffer
            self._checked.add((camera.width, camera.height))
            if self._look(blocking=True):
                rgb, alpha = self._march(out, view, camera, mark)
                self._look(blocking=True)
        elif look:
            self._look(blocking=False)
        rgb = rgb + (1.0 - alpha)[:, None] * self._background(background)
        H, W = camera.height, camera.width
        return rgb.reshape(H, W, 3).clamp(0, 1), alpha.reshape(H, W)

    def _march(self, out, view, camera, mark):
        rgb, alpha = raymarch(view.origins, view.directions, out.primitives(0), self.model.cfg.raymarch,
                              camera=camera, pixels=view.grid, budget=self.budget)
        mark("march")
        return rgb, alpha

    # -------------------------------------------------------------------------------------- graphs
    def _graphable(self) -> bool:
        if not self.cfg.graph or self.graph_error is not None:
            return False
        if self.device.type != "cuda" or resolve_marcher(self.model.cfg.raymarch.marcher) != "warp":
            if not getattr(self, "_graph_note", False):
                self._graph_note = True
                log.info("graph=True needs CUDA and the Warp marcher: frames run eagerly here")
            return False
        return True

    def _replay(self, posed_vertices, joint_rotvecs, cameras, images, masks, camera, background):
        key = (id(camera), tuple(id(c) for c in cameras), tuple(tuple(i.shape) for i in images),
               None if masks is None else tuple(tuple(m.shape) for m in masks), tuple(posed_vertices.shape),
               tuple(joint_rotvecs.shape), tuple(np.asarray(background, np.float32).reshape(-1).tolist()))
        if self._graph is None or self._graph[0] != key:
            self._graph = None
            try:
                self._graph = (key, *self._capture(posed_vertices, joint_rotvecs, cameras, images, masks, camera,
                                                   background))
            except Exception as exc:  # noqa: BLE001 - any capture failure: the eager frame, said once
                self.graph_error = f"{type(exc).__name__}: {exc}"
                log.warning("capturing the frame in a CUDA graph failed (%s): frames run eagerly", self.graph_error)
                return self._drive(posed_vertices, joint_rotvecs, cameras, images, masks, camera, background)
        _, graph, static_in, static_out = self._graph
        for dst, src in zip(static_in, [posed_vertices, joint_rotvecs, *images, *(masks or [])], strict=True):
            dst.copy_(src, non_blocking=True)
        graph.replay()
        self._look(blocking=False)
        return tuple(t.clone() for t in static_out)

    def _capture(self, posed_vertices, joint_rotvecs, cameras, images, masks, camera, background):
        """(graph, static inputs, static outputs) of one driven frame; the warm-up frames run first on
        the capture stream (Warp kernels load, cuDNN picks its algorithms, the pair buffer is sized)."""
        from uvatar.geometry.warp_torch import capture_graph

        dev = self.device
        static_in = [t.detach().clone() for t in [posed_vertices, joint_rotvecs, *images, *(masks or [])]]
        n = len(images)
        sv, sr, simgs = static_in[0], static_in[1], static_in[2:2 + n]
        smasks = static_in[2 + n:] if masks is not None else None
        stream = torch.cuda.Stream(device=dev)
        stream.wait_stream(torch.cuda.current_stream(dev))
        with torch.cuda.stream(stream):
            for _ in range(2):
                self._drive(sv, sr, cameras, simgs, smasks, camera, background)
            if self.budget is not None:
                self._look(blocking=True)
        torch.cuda.current_stream(dev).wait_stream(stream)
        graph, static_out = capture_graph(
            lambda: self._drive(sv, sr, cameras, simgs, smasks, camera, background, look=False), stream)
        return graph, static_in, static_out
