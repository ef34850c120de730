"""One DVA training step on the device, and the step captured whole in a CUDA graph
(``TrainConfig.graph``).

A step is split where the host ends: :func:`step_inputs` draws nothing itself; it turns the sampled
(frame, camera, crop) of each sample into :class:`StepInputs`, device tensors whose shapes do not change
between steps (the frame and camera indices, the crop's corner, the targets). :func:`step_loss` then
computes the step's loss from those tensors and the trainer's :class:`CameraTable` (every training
camera's matrices, lens and per-pixel rays on the device, made once) alone: nothing in it looks at the
host's data, so the same operations run on every step and a CUDA graph can record them once
(:class:`StepGraph`): forward, loss, backward, gradient clipping and the optimizer's update, replayed
each step after the step's inputs are copied into the graph's own. What would differ between steps is
in :class:`StepLayout`, the graph's key: a new layout (the correctives switched on after warm-up, a
grown pair buffer) is captured again.

The eager step (:meth:`uvatar.dva.train.Trainer.train_step` without ``graph``) runs the same
:func:`step_loss`, so a replayed step and an eager one compute the same numbers.
"""

from __future__ import annotations

import logging
import random
from dataclasses import dataclass, fields

import numpy as np
import torch

from uvatar.dva.dataset import mask_box
from uvatar.dva.model import pixel_rays
from uvatar.dva.raymarch_cull import DeviceCamera, PixelGrid

log = logging.getLogger(__name__)

#: eager steps of a layout run on the graph's stream before it is captured (the optimizer's state and
#: cuDNN's algorithms are made there, Warp's kernels loaded); the first capture of a trainer takes two
WARMUP_STEPS = 2
#: captures tried per step layout before its steps run eagerly for good (a failed capture is retried after
#: one more eager step: on an H200 a capture failed or held from one run to the next, issue 39)
CAPTURE_TRIES = 3


def target_pixels(image: np.ndarray, mask: np.ndarray, pixels: np.ndarray, background: np.ndarray,
                  mode: str = "mask") -> np.ndarray:
    """(N, 3) float32 in [0, 1]: what the render at ``pixels`` (N, 2) integer (x, y) is compared with.
    image (H, W, 3) uint8, mask (H, W) bool, background (3,) the colour the render is composited over;
    mode "mask" or "random" (:class:`~uvatar.dva.model.TrainConfig` ``background``) puts that colour
    wherever the mask is off, "photo" keeps the photo."""
    x, y = pixels[:, 0], pixels[:, 1]
    out = image[y, x].astype(np.float32) / 255.0
    if mode in ("mask", "random"):
        out = np.where(mask[y, x][:, None], out, np.asarray(background, np.float32)[None])
    return out


def crop_targets(image: np.ndarray, mask: np.ndarray, corner, size: int, background: np.ndarray,
                 mode: str = "mask") -> np.ndarray:
    """(3, size, size) float32: :func:`target_pixels` of the square crop whose top-left pixel is
    ``corner`` (x, y), by slicing (the same values as the crop's pixels listed row-major)."""
    x, y = (int(v) for v in corner)
    out = image[y:y + size, x:x + size].astype(np.float32) / 255.0
    if mode in ("mask", "random"):
        out = np.where(mask[y:y + size, x:x + size][..., None], out, np.asarray(background, np.float32))
    return np.ascontiguousarray(out.transpose(2, 0, 1))


def patch_pixels(mask: np.ndarray, size: int, rng: random.Random, box=()) -> np.ndarray:
    """(size*size, 2) integer (x, y) pixels of a square crop whose centre lies in the mask's bounding
    box (grown by half a patch), clipped to the image. ``box``: the mask's :func:`mask_box`, where the
    caller keeps it (a training step draws crops from the same masks step after step)."""
    H, W = mask.shape
    size = min(size, H, W)
    box = mask_box(mask) if box == () else box
    if box is not None:
        cy = rng.randint(box[0], box[1])
        cx = rng.randint(box[2], box[3])
    else:
        cy, cx = rng.randrange(H), rng.randrange(W)
    y0 = int(np.clip(cy - size // 2, 0, H - size))
    x0 = int(np.clip(cx - size // 2, 0, W - size))
    yy, xx = np.mgrid[y0:y0 + size, x0:x0 + size]
    return np.stack([xx.ravel(), yy.ravel()], 1)


class CameraTable:
    """The training cameras on the device, made once per trainer, so that a step finds its samples'
    cameras and rays by index (device tensors) instead of the host making them: K (C, 3, 3) pixels,
    R (C, 3, 3), T (C, 3) metres, lens (C, 5) (OpenCV k1, k2, p1, p2, k3), centres (C, 3) metres,
    ``distorted`` (host bools: whether each lens bends rays), and every pixel's unit ray direction
    (float32, each camera's H x W pixels row-major, one after the other: ``directions`` (sum H*W, 3),
    camera c's from ``offsets[c]``, ``widths[c]`` pixels a row), computed as :func:`pixel_rays` does
    (lens distortion removed). ``sizes``: each camera's (H, W), its images' size.

    A rig whose table would exceed ``max_ray_bytes`` (many cameras of many pixels: 100 cameras of 4096 x
    2668 take 13 GB) keeps no rays (``directions`` None): its steps make each crop's rays on the host
    and send them over with the step's inputs (:func:`step_inputs`), as the steps did before."""

    def __init__(self, cameras, sizes, device, max_ray_bytes: int = 2 << 30):
        from uvatar.devices import to_device_async

        pixels = sum(H * W for H, W in sizes)
        directions, offsets, total = [], [], 0
        for cam, (H, W) in zip(cameras, sizes, strict=True):
            if pixels * 12 <= max_ray_bytes:
                ys, xs = np.mgrid[0:H, 0:W]
                directions.append(pixel_rays(cam, np.stack([xs.ravel(), ys.ravel()], 1), "cpu")[1])
            offsets.append(total)
            total += H * W
        lens = np.stack([np.pad(np.asarray(getattr(c, "dist", np.zeros(5)), np.float64).reshape(-1), (0, 5))[:5]
                         for c in cameras])

        def up(array, dtype=torch.float32):
            return to_device_async(array, device, dtype)

        self.K, self.R = up(np.stack([c.K for c in cameras])), up(np.stack([c.R for c in cameras]))
        self.T = up(np.stack([np.asarray(c.T, np.float64).reshape(3) for c in cameras]))
        self.lens, self.centres = up(lens), up(np.stack([c.center for c in cameras]))
        self.distorted = tuple(bool(np.any(x != 0)) for x in lens)
        self.directions = up(torch.cat(directions)) if directions else None
        self.offsets = up(np.asarray(offsets), torch.int64)
        self.widths = up(np.asarray([W for _, W in sizes]), torch.int64)

    def device_cameras(self, cameras: torch.Tensor, distorted) -> list[DeviceCamera]:
        """Cameras ``cameras`` (B,) int64 (on the device) as :class:`DeviceCamera` s; ``distorted``: the
        host's bool for each (:class:`StepLayout`)."""
        K, R, T, lens = (x[cameras] for x in (self.K, self.R, self.T, self.lens))
        return [DeviceCamera(K[b], R[b], T[b], lens[b], d) for b, d in enumerate(distorted)]

    def batch(self, cameras: torch.Tensor, distorted) -> tuple:
        """(K (B, 3, 3), R (B, 3, 3), T (B, 3), lens (B, 5) or None) of cameras ``cameras`` (B,) int64 (on
        the device), as :func:`~uvatar.dva.raymarch_crops.render_crops` takes them; ``distorted``: the
        host's bool for each (:class:`StepLayout`): the lenses are left out where none bends rays."""
        return (self.K[cameras], self.R[cameras], self.T[cameras], self.lens[cameras] if any(distorted) else None)

    def crop_rays(self, cameras: torch.Tensor, corners: torch.Tensor, size: int):
        """(origins, directions) (B, size * size, 3) of square crops, row-major from each crop's top-left
        pixel ``corners`` (B, 2) int64 (x, y), in cameras ``cameras`` (B,) int64: a gather, no host (a
        table that keeps rays: ``directions`` not None)."""
        r = torch.arange(size, device=corners.device)
        rows = (corners[:, 1:2] + r)[:, :, None] * self.widths[cameras][:, None, None]
        index = self.offsets[cameras][:, None, None] + rows + (corners[:, 0:1] + r)[:, None, :]
        directions = self.directions[index.reshape(len(cameras), -1)]
        return self.centres[cameras][:, None, :].expand_as(directions), directions


@dataclass
class StepInputs:
    """One step's B samples on the training device (each a P x P pixel crop; N = P * P rays):

    frames (B,) int64 bank frames; cameras (B,) int64 training cameras (their matrices and rays: the
    trainer's :class:`CameraTable`); textures (B, 4, R, R) the image features' input; vertices (B, V, 3)
    metres and rotvecs (B, J, 3) radians, the fitted bodies (None where the step re-poses them with the
    learned offsets); corners (B, 2) int64 each crop's top-left pixel (x, y); targets (B, 3, P, P) in
    [0, 1]; masks (B, P, P) in {0, 1}; backgrounds (B, 3) the colour each render is composited over;
    origins, directions (B, N, 3) the crops' rays, made on the host where the camera table keeps none
    (else None: gathered from the table)."""

    frames: torch.Tensor
    cameras: torch.Tensor
    textures: torch.Tensor
    vertices: torch.Tensor | None
    rotvecs: torch.Tensor | None
    corners: torch.Tensor
    targets: torch.Tensor
    masks: torch.Tensor
    backgrounds: torch.Tensor
    origins: torch.Tensor | None = None
    directions: torch.Tensor | None = None

    def tensors(self) -> list[torch.Tensor]:
        return [t for t in (getattr(self, f.name) for f in fields(self)) if t is not None]

    def clone(self) -> StepInputs:
        return StepInputs(*(None if t is None else t.clone() for t in (getattr(self, f.name) for f in fields(self))))

    def copy_(self, other: StepInputs) -> None:
        """Copy ``other``'s values into these tensors (a graph's static inputs), on the device's queue."""
        for dst, src in zip(self.tensors(), other.tensors(), strict=True):
            dst.copy_(src, non_blocking=True)


@dataclass(frozen=True)
class StepLayout:
    """What a step's operations depend on besides its input tensors (a captured step's key): samples
    ``batch``, crop side ``patch`` (pixels), whether the primitives' ``correctives`` are on, whether the
    step ``reposes`` the bodies with the learned pose offsets, each sample camera's lens bending rays
    (``distorted``, the culling's branch), and the marcher's pair buffer ``pairs`` (per marcher call: the
    batch's crops, or one crop where they render sample after sample, :func:`renders_batched`)."""

    batch: int
    patch: int
    correctives: bool
    reposes: bool
    distorted: tuple[bool, ...]
    pairs: int


#: render a step's crops in one marcher call (:mod:`uvatar.dva.raymarch_crops`) where the marcher is Warp;
#: False: sample after sample, the reference (the torch marcher always is)
BATCHED_CROPS = True


def renders_batched(trainer) -> bool:
    """Whether ``trainer``'s steps render their crops in one marcher call (:data:`BATCHED_CROPS`)."""
    from uvatar.dva.raymarch import resolve_marcher

    return BATCHED_CROPS and resolve_marcher(trainer.model.cfg.raymarch.marcher) == "warp"


def budget_rays(trainer, batch: int, patch: int) -> int:
    """The rays one marcher call of a step renders (what its pair buffer is sized for): the batch's
    crops where they go in one call (:func:`renders_batched`), else one crop."""
    return patch * patch * (batch if renders_batched(trainer) else 1)


def step_inputs(trainer, frames, cams, textures, pixels, backgrounds, correctives: bool):
    """(:class:`StepInputs`, :class:`StepLayout`) of a sampled batch (:meth:`Trainer.sample`'s): the host's
    arrays stacked once per kind and sent to the device without blocking (pinned memory on CUDA)."""
    from uvatar.devices import to_device_async

    dev, t, bank = trainer.device, trainer.cfg.train, trainer.bank
    P = int(round(np.sqrt(pixels[0].shape[0])))
    corners = np.stack([pix[0] for pix in pixels])  # the crops are row-major squares (patch_pixels)
    targets = [crop_targets(bank.images[f][c], bank.masks[f][c], corner, P, bg, t.background)
               for f, c, corner, bg in zip(frames, cams, corners, backgrounds, strict=True)]
    masks = [bank.masks[f][c][y:y + P, x:x + P].astype(np.float32) for f, c, (x, y) in zip(frames, cams, corners,
                                                                                               strict=True)]
    reposes = trainer.reposes(correctives)
    host = torch.tensor(frames)

    def up(array, dtype=torch.float32):
        return to_device_async(array, dev, dtype)

    vertices, rotvecs = (None, None) if reposes else (up(bank.vertices[host]), up(bank.rotvecs[host]))
    inputs = StepInputs(
        frames=up(host, torch.int64), cameras=up(torch.tensor(cams), torch.int64), textures=textures,
        vertices=vertices, rotvecs=rotvecs, corners=up(corners, torch.int64), targets=up(np.stack(targets)),
        masks=up(np.stack(masks)), backgrounds=up(np.stack([np.asarray(b, np.float32) for b in backgrounds])))
    if trainer.cameras.directions is None:  # a rig too large for a table of rays: the host makes them
        rays = [pixel_rays(bank.cams[c], pix, "cpu") for c, pix in zip(cams, pixels, strict=True)]
        inputs.origins, inputs.directions = (up(torch.stack([r[i] for r in rays])) for i in (0, 1))
    budget = trainer._budget(budget_rays(trainer, len(frames), P))
    layout = StepLayout(len(frames), P, bool(correctives), reposes,
                        tuple(trainer.cameras.distorted[c] for c in cams), 0 if budget is None else budget.capacity)
    return inputs, layout


def step_loss(trainer, inputs: StepInputs, layout: StepLayout, host_frames=None):
    """(total loss (differentiable 0-dim), terms {name: detached 0-dim}, with "total" and "mse") of one
    step, from the device tensors alone. ``host_frames`` (B,) int64: the frames on the host, which the
    host re-posing path (``pose_on_device=False``) and the bodies' shapes need."""
    model, corrections, t = trainer.model, trainer.corrections, trainer.cfg.train
    P = layout.patch
    correctives = layout.correctives
    if layout.reposes:
        vertices, rotvecs = trainer._posed(host_frames, inputs.frames)
    else:
        vertices, rotvecs = inputs.vertices, inputs.rotvecs
    table = trainer.cameras
    out = model(vertices, rotvecs, inputs.textures, table.centres[inputs.cameras], t.precision, compact=True,
                correctives=correctives, decode=trainer.decode)
    budget = trainer._budget(budget_rays(trainer, layout.batch, P))
    origins, directions = (inputs.origins, inputs.directions) if inputs.directions is not None \
        else table.crop_rays(inputs.cameras, inputs.corners, P)
    B = layout.batch
    if renders_batched(trainer):  # one marcher call for the batch (raymarch_crops)
        from uvatar.dva.raymarch_crops import render_crops
        from uvatar.dva.raymarch_ref import Primitives

        rgb, alpha = render_crops(Primitives(out.positions, out.rotations, out.scales, out.payload), origins,
                                  directions, table.batch(inputs.cameras, layout.distorted), inputs.corners, P,
                                  model.cfg.raymarch, budget)
        if corrections is not None:
            rgb = corrections.colour(rgb, alpha, inputs.cameras[:, None])
        rgb = rgb + (1.0 - alpha)[..., None] * inputs.backgrounds[:, None, :]
        pred, alphas = rgb.transpose(1, 2).reshape(B, 3, P, P).contiguous(), alpha.reshape(B, P, P)  # laid out
        # as the reference's stack: the loss's sums add in the same order
    else:  # the reference: sample after sample
        preds, per_sample = [], []
        for b, camera in enumerate(table.device_cameras(inputs.cameras, layout.distorted)):
            rgb, alpha = model.render_rays(out, b, origins[b], directions[b], None, camera=camera,
                                           pixels=PixelGrid.crop(P, inputs.corners[b]), budget=budget)
            if corrections is not None:
                rgb = corrections.colour(rgb, alpha, inputs.cameras[b:b + 1])
            rgb = rgb + (1.0 - alpha)[:, None] * inputs.backgrounds[b]
            preds.append(rgb.T.reshape(3, P, P))
            per_sample.append(alpha.reshape(P, P))
        pred, alphas = torch.stack(preds), torch.stack(per_sample)
    total, terms = trainer.loss.terms(pred, inputs.targets, alphas, inputs.masks, out.scales,
                                      model.rest_scales, out.motion if correctives else None, out.learned_rgb,
                                      out.payload[:, :, 3])
    if corrections is not None:
        for k, v in corrections.prior(inputs.frames, inputs.cameras).items():
            total = total + v
            terms[k] = v.detach()
    terms["total"] = total.detach()
    terms["mse"] = ((pred - inputs.targets) ** 2).mean().detach()
    return total, terms


class StepGraph:
    """A trainer's training step captured in a CUDA graph (``TrainConfig.graph``) and replayed.

    Per :class:`StepLayout`: :data:`WARMUP_STEPS` eager steps on the graph's stream (the optimizer's
    state, cuDNN's algorithms, Warp's modules; one after the first capture), then the next step is
    captured (``torch.cuda.graph`` with Warp told of the capture, as
    :class:`~uvatar.dva.frame.FrameRenderer` does) and every later step of that layout copies its inputs
    into the graph's and replays it: forward, loss, backward, clipping, the update (fused Adam with a
    device learning rate and ``found_inf``) with no launch from Python. A failed capture is logged and
    counted in ``failures``; the step runs eagerly and the capture is tried again after one more eager
    step, up to :data:`CAPTURE_TRIES` times per layout. Then ``error`` keeps the last failure and the
    steps run eagerly from then on."""

    def __init__(self, trainer):
        self.trainer = trainer
        self.key: StepLayout | None = None
        self.graph = None
        self.inputs: StepInputs | None = None
        self.terms: dict | None = None
        self.error: str | None = None
        self.failures = 0      # failed captures (all layouts)
        self.tries = 0         # failed captures of the current layout
        self.warm = 0          # eager steps run on the stream for the current key
        self.captures = 0
        self.replays = 0
        self._values: torch.Tensor | None = None  # the terms, written by each replay
        self.stream = torch.cuda.Stream(device=trainer.device) if trainer.device.type == "cuda" else None

    def step(self, inputs: StepInputs, layout: StepLayout, host_frames) -> dict:
        """One training step of ``inputs``: eager warm-up, capture or replay; its terms (device tensors)."""
        tr = self.trainer
        if layout != self.key:
            self.key, self.graph, self.inputs, self.terms, self.warm, self.tries = layout, None, None, None, 0, 0
        if self.graph is None and self.warm < (WARMUP_STEPS if self.captures == 0 else 1) + self.tries:
            self.warm += 1
            return self._on_stream(lambda: tr._eager_step(inputs, layout, host_frames))
        if self.graph is None:
            try:
                self._capture(inputs, layout, host_frames)
            except Exception as exc:  # noqa: BLE001 - any capture failure: eager steps, said
                self.graph = None
                self.failures += 1
                self.tries += 1
                why = f"{type(exc).__name__}: {exc}"
                log.debug("the failed capture's traceback", exc_info=True)
                if self.tries >= CAPTURE_TRIES:
                    self.error = why
                log.warning("capturing the training step in a CUDA graph failed (%s, try %d of %d): %s", why,
                            self.tries, CAPTURE_TRIES, "steps run eagerly" if self.error else "tried again")
                tr.opt.zero_grad(set_to_none=True)
                return tr._eager_step(inputs, layout, host_frames)
        self.inputs.copy_(inputs)
        self.graph.replay()
        self.replays += 1
        names = list(self.terms)
        values = self._values.clone()  # one copy: the next replay overwrites the graph's own
        return {k: values[i] for i, k in enumerate(names)}

    def _on_stream(self, fn):
        """Run ``fn`` on the graph's stream (where its warm-up must run), ordered after the work queued
        before it and before the work queued after it."""
        if self.stream is None:
            return fn()
        dev = self.trainer.device
        self.stream.wait_stream(torch.cuda.current_stream(dev))
        with torch.cuda.stream(self.stream):
            out = fn()
        torch.cuda.current_stream(dev).wait_stream(self.stream)
        return out

    def _capture(self, inputs: StepInputs, layout: StepLayout, host_frames) -> None:
        """Record the step of ``layout`` on a copy of ``inputs`` (the graph's static inputs)."""
        tr = self.trainer
        static = inputs.clone()
        terms: dict = {}

        def one_step():
            total, got = step_loss(tr, static, layout, host_frames)
            tr._update_on_device(total)
            terms.update(got)
            return torch.stack([v.float() for v in got.values()])

        tr.opt.zero_grad(set_to_none=True)  # the gradients are the graph's own, written by each replay
        self.graph, self._values = self._record(one_step)
        self.inputs, self.terms = static, terms
        self.captures += 1
        log.info("the training step is captured in a CUDA graph (%s)", layout)

    def _record(self, fn):
        """(a CUDA graph of ``fn``, its output) captured on the graph's stream
        (:func:`~uvatar.geometry.warp_torch.capture_graph`)."""
        from uvatar.geometry.warp_torch import capture_graph

        return capture_graph(fn, self.stream)
