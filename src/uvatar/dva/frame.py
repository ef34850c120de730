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

No host sync in the decoding: the correctives switch is read once, at construction; rays and pixels
of the last camera are kept on the device. The marcher itself still reads back its pair count and step
count (:mod:`uvatar.dva.raymarch_warp`), two small syncs per frame.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from uvatar.dva.model import DvaOutput, pixel_rays
from uvatar.dva.raymarch import raymarch
from uvatar.precision import FastPathConfig


def _no_mark(stage: str) -> None:
    """The default stage hook of :class:`FrameRenderer`: nothing."""


class FrameConfig(FastPathConfig):
    """The fast frame's path (:class:`~uvatar.precision.FastPathConfig`): precision of the encoders
    and decoders, compile, compile_mode, channels_last."""


class _Decode(nn.Module):
    """(pose maps, image texture, view features, skip) -> motion (B, 9, W, W), payload (B, K, 4, S, S, S)
    fp32: the model's encoders and decoders, under autocast when ``dtype`` is not fp32."""

    def __init__(self, model, dtype: torch.dtype, channels_last: bool):
        super().__init__()
        self.pose_encoder, self.image_encoder, self.decoder = model.pose_encoder, model.image_encoder, model.decoder
        self.dtype, self.channels_last = dtype, channels_last

    def forward(self, pose_maps, image_texture, f_view, skip_colour=None, skip_weight=None):
        if self.channels_last:
            pose_maps, image_texture, f_view = (t.contiguous(memory_format=torch.channels_last)
                                                for t in (pose_maps, image_texture, f_view))
        with torch.autocast(pose_maps.device.type, dtype=self.dtype, enabled=self.dtype != torch.float32):
            f_pose = self.pose_encoder(pose_maps)
            f_img = self.image_encoder(image_texture)
            skip = None if skip_colour is None else (skip_colour, skip_weight)
            motion, payload = self.decoder.payload(f_pose, f_img, f_view, skip, torch.float32)
        return motion.float(), payload


class FrameRenderer:
    """Decode and render frames of a trained :class:`~uvatar.dva.model.DvaModel` the fast way.

    ``decode(posed_vertices (B, V, 3), joint_rotvecs (B, J, 3), image_texture (B, 4, R, R),
    camera_centers (B, 3)) -> DvaOutput`` (``learned_rgb`` is the payload's RGB);
    ``render(posed_vertices (V, 3), joint_rotvecs (J, 3), image_texture (4, R, R), camera, background)
    -> rgb (H, W, 3) in [0, 1], alpha (H, W)``, torch tensors on the model's device (nothing is copied
    back to the host). The model is used in place (eval mode; ``channels_last`` changes its parameters'
    memory layout, not their values). ``mark(stage)``, when given, is called as each stage of a frame
    ends ("unwrap", "inputs", "encode_decode", "place", "march"): what ``bench/dva_frame.py --profile``
    times."""

    def __init__(self, model, cfg: FrameConfig | None = None):
        self.model, self.cfg = model.eval(), cfg or FrameConfig()
        self.correctives = bool(model.correctives_on)
        self._decode = self.cfg.prepare(_Decode(model, self.cfg.dtype, self.cfg.channels_last))
        self._camera, self._rays = None, None

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

    def rays(self, camera):
        """origins, directions (H*W, 3) and pixels (H*W, 2) of every pixel of ``camera``, on the model's
        device; kept for the last camera."""
        if camera is not self._camera:
            dev = self.model.texel_weights.device
            yy, xx = np.mgrid[:camera.height, :camera.width]
            pix = np.stack([xx.ravel(), yy.ravel()], 1)
            o, d = pixel_rays(camera, pix, dev)
            self._camera, self._rays = camera, (o, d, torch.as_tensor(pix, device=dev))
        return self._rays

    @torch.no_grad()
    def drive(self, posed_vertices, joint_rotvecs, cameras, images, masks, camera, background=(0.0, 0.0, 0.0),
              mark=_no_mark):
        """A telepresence frame: driving views (cameras, images (H, W, 3) and masks (H, W), torch on the
        device) + the frame's pose -> ``camera``'s rgb (H, W, 3), alpha (H, W). The views are unwrapped on
        the device (:func:`uvatar.dva.unwrap_device.driving_texture_device`, Warp), then :meth:`render`."""
        from uvatar.dva.unwrap_device import driving_texture_device

        tex = driving_texture_device(self.model, posed_vertices, cameras, images, masks)
        mark("unwrap")
        return self.render(posed_vertices, joint_rotvecs, tex, camera, background, mark)

    @torch.no_grad()
    def render(self, posed_vertices, joint_rotvecs, image_texture, camera, background=(0.0, 0.0, 0.0),
               mark=_no_mark):
        dev = posed_vertices.device
        center = torch.as_tensor(camera.center, dtype=torch.float32, device=dev)[None]
        out = self.decode(posed_vertices[None], joint_rotvecs[None], image_texture[None].to(dev), center, mark)
        o, d, pix = self.rays(camera)
        rgb, alpha = raymarch(o, d, out.primitives(0), self.model.cfg.raymarch, camera=camera, pixels=pix)
        mark("march")
        bg = torch.as_tensor(np.asarray(background, np.float32), device=dev)
        rgb = rgb + (1.0 - alpha)[:, None] * bg
        H, W = camera.height, camera.width
        return rgb.reshape(H, W, 3).clamp(0, 1), alpha.reshape(H, W)
