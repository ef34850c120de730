"""Train a DVA avatar on a multi-view source (``uvatar train dva``).

Each step draws ``batch`` random (frame, training camera) pairs, renders a random ``patch`` x ``patch``
crop around the person in that camera and fits it (losses in :mod:`uvatar.dva.losses`). Image features
follow the paper's two-stage curriculum: for the first ``all_views_iters`` steps they come from every
training view, afterwards from ``driving_views`` (3) random training views. Primitive correctives are off
for the first ``warmup_iters`` steps. The run folder holds ``checkpoint.pt`` (written atomically every
``checkpoint_every`` steps and at the end; ``resume=True`` continues from it), ``run.json`` and
TensorBoard logs in ``tb/``. The checkpoint also holds the sampling RNG, torch's RNG and the seconds
already trained (time budget and learning-rate clock), so a resumed run takes the same steps as an
uninterrupted one; a run folder with a checkpoint is never replaced without ``resume``.

Under ``torchrun`` (:mod:`uvatar.distributed`) every process draws the same global batch and renders
its share (samples ``rank::world``); the gradients are averaged over the processes (one all-reduce per
step, gloo on CPU, NCCL on GPUs), so the steps are those of one process at the same batch. Rank 0
alone shows progress and writes the run folder.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
import random
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from uvatar.distributed import DistContext, all_sum, distributed_context
from uvatar.dva.corrections import FitParams, TrainingCorrections
from uvatar.dva.dataset import FrameBank, pose_corrected, pose_vertices
from uvatar.dva.losses import EMPTY_OPACITY, DvaLoss, Vgg19Features
from uvatar.dva.model import DvaConfig, DvaModel, EncodeDecode, TrainConfig
from uvatar.dva.train_step import CameraTable, patch_pixels, step_inputs, step_loss
from uvatar.errors import InputError, UvatarError
from uvatar.io_utils import atomic_path, sweep_partial_writes, write_json

log = logging.getLogger(__name__)
CHECKPOINT = "checkpoint.pt"


def make_body(name: str, device="cpu", model_dir=None):
    """The body model a run was trained with ("toy" is the test tube of :mod:`uvatar.dva.toy`);
    ``model_dir``: the SMPL/SMPL-X files (default ``$UVATAR_SMPL_DIR``; anny needs none)."""
    if name == "toy":
        from uvatar.dva.toy import ToyBody

        return ToyBody().to(device)
    from uvatar.body.registry import BODY_MODELS, load_body_model

    if str(name).lower() not in BODY_MODELS:
        raise InputError("body model", f"unknown body model {name!r}; choose one of {', '.join(BODY_MODELS)}")
    return load_body_model(name, model_dir=model_dir, device=device)


#: ``torch.compile`` modes that capture CUDA graphs (cudagraph trees: a step marks its beginning)
CUDA_GRAPH_MODES = ("reduce-overhead", "max-autotune")


def _step_decode(model, train: TrainConfig):
    """The encoders and decoders of a training step: the model's :class:`~uvatar.dva.model.EncodeDecode`
    in ``train.precision`` (channels_last when ``train.channels_last``: the model's convolution weights
    too, in place), through ``torch.compile`` in ``train.compile_mode`` when ``train.compile``; None where
    the model's colour skip makes the step take the reference decoder (with ``compile`` or
    ``channels_last``: a warning that those steps use neither)."""
    if model.cfg.features.colour_skip:
        if train.compile or train.channels_last:
            log.warning("compile / channels_last: the colour skip's training steps use the reference decoders, "
                        "eager and NCHW")
        return None
    from uvatar.precision import FastPathConfig

    path = FastPathConfig(precision=train.precision, compile=train.compile, compile_mode=train.compile_mode,
                          channels_last=train.channels_last)
    return path.prepare(EncodeDecode(model, path.dtype, channels_last=train.channels_last))


def save_checkpoint(path: Path, model, optimizer, step: int, meta: dict, clock: dict | None = None,
                    corrections=None) -> None:
    """Write a run's checkpoint atomically. clock: what a resume needs to take the same steps
    (``rng``: the sampling RNG state, ``torch_rng``, ``seconds`` trained so far); corrections: the
    :class:`~uvatar.dva.corrections.TrainingCorrections` learned beside the model."""
    opt = optimizer.state_dict() if optimizer else None
    if opt is not None:  # a captured step's device learning rates saved as numbers: any trainer resumes it
        opt["param_groups"] = [{**g, "lr": float(g["lr"]), "capturable": False} for g in opt["param_groups"]]
    state = {"model": model.state_dict(), "optimizer": opt,
             "step": step, "config": model.cfg.to_dict(), "meta": meta, "clock": clock,
             "corrections": corrections.state_dict() if corrections is not None else None}
    with atomic_path(path, suffix=".pt") as tmp:
        torch.save(state, tmp)


def load_run(run_dir, device="cpu", body_model=None, model_dir=None, marcher: str | None = None):
    """(model, body, meta, step) from a run folder's checkpoint. ``body_model``: must be the run's
    own when given; ``model_dir``: where its SMPL/SMPL-X files are (default: the training run's);
    ``marcher``: the ray marcher to render with (``RaymarchConfig.marcher``; default: the run's)."""
    path = Path(run_dir) / CHECKPOINT
    if not path.is_file():
        raise InputError(path, "no DVA checkpoint here (train with `uvatar train dva` first)")
    try:
        state = torch.load(path, map_location=device, weights_only=False)
        cfg = DvaConfig.from_dict(state["config"])
        if marcher is not None:
            cfg.raymarch = dataclasses.replace(cfg.raymarch, marcher=marcher)
        meta = state["meta"]
    except Exception as exc:  # noqa: BLE001 - any unreadable checkpoint is the same user error
        raise InputError(path, f"unreadable checkpoint ({exc.__class__.__name__}: {exc})") from None
    if body_model and body_model != meta["body_model"]:
        raise InputError(path, f"was trained with body model {meta['body_model']!r}, not {body_model!r}")
    body = make_body(meta["body_model"], device, model_dir or meta.get("model_dir"))
    model = DvaModel(cfg, body.template, meta["conditioning_joints"]).to(device)
    model.load_state_dict(state["model"])
    model.eval()
    return model, body, meta, state["step"]


class StepTerms(Mapping):
    """A training step's loss terms ({name: float}, with "total" and "psnr"), kept as device tensors until
    one is read; then all are read at once (one sync) and "psnr" is made from the batch's MSE. Reading
    also calls ``on_read`` once (the trainer's deferred warnings)."""

    def __init__(self, terms: dict, on_read=None):
        self._terms, self._on_read, self._floats = terms, on_read, None

    def _values(self) -> dict:
        if self._floats is None:
            keys = list(self._terms)
            tensors = [v for v in self._terms.values() if isinstance(v, torch.Tensor)]
            read = iter(torch.stack([v.detach().reshape(()).double() for v in tensors]).tolist() if tensors else [])
            floats = {k: next(read) if isinstance(self._terms[k], torch.Tensor) else float(self._terms[k])
                      for k in keys}
            floats["psnr"] = float(-10 * np.log10(max(floats.pop("mse"), 1e-10)))
            self._floats = floats
            if self._on_read is not None:
                self._on_read()
        return self._floats

    def __getitem__(self, key):
        return self._values()[key]

    def __iter__(self):
        return iter(self._values())

    def __len__(self) -> int:
        return len(self._values())

    def __repr__(self) -> str:
        return f"StepTerms({self._values()!r})"


class Trainer:
    """Holds the model, the data bank and the optimizer; ``run()`` trains until iters or minutes."""

    def __init__(self, source, out_dir, cfg: DvaConfig, body=None, device="cpu", vgg_weights=None,
                 resume=False, seed=0, progress=True, body_model=None, model_dir=None,
                 ctx: DistContext | None = None, pose_on_device: bool | None = None):
        """``pose_on_device``: re-pose the body with the learned pose offsets on the training device
        (a copy of the body model and of the fits there; default: when the device is not the CPU).
        False is the host path (the body model as loaded, on the CPU), the reference twin; True on a
        CPU trainer runs the device path's code there (what the tests compare)."""
        self.source, self.out = source, Path(out_dir)
        self.ctx = ctx or DistContext(device=torch.device(device))
        self.device, self.progress = self.ctx.device, progress and self.ctx.is_main
        if self.device.type == "cuda":  # every step decodes the same shapes: let cuDNN pick its fastest algorithms once
            torch.backends.cudnn.benchmark = True
        self.rng = random.Random(seed)
        self.seconds = 0.0  # trained so far, over every resumed part of the run
        torch.manual_seed(seed)
        self.out.mkdir(parents=True, exist_ok=True)
        if self.ctx.is_main:
            sweep_partial_writes(self.out)  # temp files of writes a kill cut short
        ckpt = self.out / CHECKPOINT
        state = None
        exists = ckpt.is_file()
        self.ctx.barrier()  # every rank has looked before rank 0 writes
        if exists and not resume:
            raise UvatarError(f"{self.out}: holds a checkpoint; resume=True continues it, or pick a new folder")
        if exists:
            try:
                state = torch.load(ckpt, map_location=self.device, weights_only=False)
            except Exception as exc:  # noqa: BLE001 - any unreadable checkpoint is the same user error
                raise InputError(ckpt, f"unreadable checkpoint ({exc.__class__.__name__}: {exc})") from None
            caller = cfg  # how to render and compile, not what was learned: the caller's
            cfg = DvaConfig.from_dict(state["config"])  # the run's own config wins on resume
            cfg.raymarch = dataclasses.replace(cfg.raymarch, marcher=caller.raymarch.marcher)
            cfg.train = dataclasses.replace(cfg.train, compile=caller.train.compile,
                                            compile_mode=caller.train.compile_mode,
                                            channels_last=caller.train.channels_last, graph=caller.train.graph)
            log.info("resuming from %s at step %d", ckpt, state["step"])
        self.cfg = cfg
        if state is not None and body_model and body_model != state["meta"]["body_model"]:
            raise InputError(ckpt, f"was trained with body model {state['meta']['body_model']!r}, not {body_model!r}")
        body_name = getattr(body, "name", None) or body_model or source.body_model
        self.body = body if body is not None else make_body(body_name, "cpu", model_dir)
        joints = tuple(getattr(self.body, "conditioning_joints", range(self.body.num_joints)))
        self.model = DvaModel(cfg, self.body.template, joints).to(self.device)
        self.decode = _step_decode(self.model, cfg.train)
        self.bank = FrameBank(source, self.body, self.model.image_raster, self.body.template,
                              source.train_frames, source.train_cameras, progress)
        self.cameras = CameraTable(self.bank.cams, [m.shape[:2] for m in self.bank.masks[0]], self.device)
        vgg = Vgg19Features.from_file(vgg_weights).to(self.device) if vgg_weights else None
        from uvatar.dva.raymarch import resolve_marcher

        self.loss = DvaLoss(cfg.loss, vgg, kernels=resolve_marcher(cfg.raymarch.marcher)).to(self.device)
        c = cfg.corrections
        self.corrections = TrainingCorrections(c, len(self.bank), len(self.bank.cameras), joints).to(self.device) \
            if (c.pose or c.colour) else None
        groups = [{"params": list(self.model.parameters()), "lr": cfg.train.lr}]
        if self.corrections is not None:
            groups.append({"params": list(self.corrections.parameters()), "lr": c.lr})
        self.params = [p for g in groups for p in g["params"]]
        self.pose_on_device = self.device.type != "cpu" if pose_on_device is None else bool(pose_on_device)
        learns_pose = self.corrections is not None and c.pose
        self.posing = self._posing_on_device(body is not None, body_name, model_dir) \
            if learns_pose and self.pose_on_device else None
        self.budget, self.pair_overflows = None, 0
        self.step = 0
        refusal = self._graph_refusal() if cfg.train.graph else None
        if refusal:
            log.info("--graph: the training steps run eagerly here: %s", refusal)
        graphed = cfg.train.graph and refusal is None
        # on CUDA the fused kernel: one launch per step, and it skips a non-finite step on the device; a
        # captured step keeps its step counts and learning rates on the device (set_lr writes into them)
        self.opt = torch.optim.Adam(groups, fused=True, capturable=graphed) if self.device.type == "cuda" \
            else torch.optim.Adam(groups)
        self.meta = {"body_model": body_name, "model_dir": None if model_dir is None else str(model_dir),
                     "conditioning_joints": list(joints),
                     "source": str(getattr(source, "root", "")), "train_cameras": list(source.train_cameras),
                     "train_frames": list(self.bank.frames), "skipped_frames": self.bank.skipped,
                     "backgrounds": {c: self.bank.backgrounds[i].tolist() for i, c in enumerate(self.bank.cameras)},
                     "perceptual": "vgg19" if vgg else "ssim", "protocol": source.protocol,
                     "seed": int(state["meta"].get("seed", seed)) if state is not None else int(seed)}
        if state is not None:
            self.model.load_state_dict(state["model"])
            if self.corrections is not None and state.get("corrections"):
                self.corrections.load_state_dict(state["corrections"])
            if state.get("optimizer"):
                self.opt.load_state_dict(state["optimizer"])
            self.step = int(state["step"])
            clock = state.get("clock") or {}
            if "rng" in clock:
                self.rng.setstate(_tupled(clock["rng"]))
                torch.set_rng_state(clock["torch_rng"].cpu())  # map_location moved it to the device
                self.seconds = float(clock["seconds"])
            else:  # a checkpoint from before the clock was saved: continues, but not step for step
                log.warning("%s has no sampling RNG state: the resumed steps differ from an uninterrupted run", ckpt)
        # skipped updates: counted on the device where the update is (see train_step), else on the host
        self.skipped_updates = torch.zeros((), device=self.device) if self._device_skips else 0
        self.graph = None
        if graphed:
            from uvatar.dva.train_step import StepGraph

            for group in self.opt.param_groups:  # a replayed update reads its learning rate on the device
                group["capturable"] = True
                group["lr"] = torch.tensor(float(group["lr"]), device=self.device)
            self.graph = StepGraph(self)

    def sample(self):
        """This process's share of one global batch: (frame indices, camera indices, image textures
        (b,4,R,R), pixel crops [(P*P, 2)], backgrounds [(3,)] the colour each render is composited over).
        Every process draws the whole global batch (same RNG stream) and keeps samples ``rank::world``;
        one process keeps them all."""
        t = self.cfg.train
        n_cam = len(self.bank.cameras)
        frames = [self.rng.randrange(len(self.bank)) for _ in range(t.batch)]
        cams = [self.rng.randrange(n_cam) for _ in range(t.batch)]
        usable = self.bank.usable
        cams = [c if usable[f, c] else self.rng.choice(np.flatnonzero(usable[f]).tolist())   # never a view
                for f, c in zip(frames, cams, strict=True)]                                 # without the subject
        if self.step < t.all_views_iters:
            views = [list(range(n_cam))] * t.batch
        else:
            views = [self.rng.sample(range(n_cam), min(t.driving_views, n_cam)) for _ in range(t.batch)]
        if t.hide_target_view and n_cam > 1:
            views = [[v for v in vs if v != c] or [(c + 1) % n_cam] for vs, c in zip(views, cams, strict=True)]
        pixels = [patch_pixels(self.bank.masks[f][c], t.patch, self.rng, self.bank.mask_boxes[f][c])
                  for f, c in zip(frames, cams, strict=True)]
        if t.background == "random":
            backgrounds = [np.array([self.rng.random() for _ in range(3)], np.float32) for _ in frames]
        else:
            backgrounds = [self.bank.backgrounds[c] for c in cams]
        mine = slice(self.ctx.rank, None, self.ctx.world)
        frames, cams, views, pixels, backgrounds = (frames[mine], cams[mine], views[mine], pixels[mine],
                                                    backgrounds[mine])
        tex = torch.stack([self.bank.image_texture(f, v) for f, v in zip(frames, views, strict=False)])
        from uvatar.devices import to_device_async

        return frames, cams, to_device_async(tex, self.device), pixels, backgrounds

    def train_step(self) -> StepTerms:
        """One optimisation step. Returns its loss terms (and "total", "psnr") as a :class:`StepTerms`:
        they stay on the device until read (reading one reads them all: one sync), so a step run without
        reading them never waits for the device, except where noted below.

        The host samples the batch and sends it over (:func:`~uvatar.dva.train_step.step_inputs`); the
        loss is computed from the device tensors alone (:func:`~uvatar.dva.train_step.step_loss`), eagerly
        or, with ``TrainConfig.graph`` on CUDA, as the replay of a captured CUDA graph
        (:class:`~uvatar.dva.train_step.StepGraph`). On CUDA in one process nothing in the step reads the
        device back: the correctives switch is the host's step count, the marcher's pair buffer is fixed
        (``TrainConfig.pairs_per_ray``; its overflow is looked at a step late, without blocking), the
        host's data go to the device through pinned memory, and a non-finite loss or gradient skips the
        update on the device (Adam's fused kernel with ``found_inf``, as a ``GradScaler`` does; the
        skipped steps are counted in ``skipped_updates`` and warned about when the terms are next read).
        On the CPU and under torchrun the checks are made on the host as before (free on a CPU; the
        processes must agree)."""
        t = self.cfg.train
        correctives = self.step >= t.warmup_iters
        self.model.correctives_on.fill_(correctives)
        frames, cams, tex, pixels, backgrounds = self.sample()
        inputs, layout = step_inputs(self, frames, cams, tex, pixels, backgrounds, correctives)
        host_frames = torch.tensor(frames)
        if self.graph is not None and self.graph.error is None:
            terms = self.graph.step(inputs, layout, host_frames)
        else:
            terms = self._eager_step(inputs, layout, host_frames)
        self.step += 1
        if self.ctx.active:  # the global batch's terms: the mean of the processes' equal shares
            keys = sorted(terms)
            mean = all_sum(torch.tensor([float(terms[k]) for k in keys], dtype=torch.float64)) / self.ctx.world
            terms = dict(zip(keys, mean.tolist(), strict=True))
        self._look_at_budget()
        return StepTerms(terms, self._report_skips)

    def _eager_step(self, inputs, layout, host_frames) -> dict:
        """The step run operation by operation: loss, backward, clip, update; its terms."""
        t = self.cfg.train
        if t.compile and t.compile_mode in CUDA_GRAPH_MODES and self.device.type == "cuda":
            torch.compiler.cudagraph_mark_step_begin()  # the last step's graphed outputs are no longer read
        total, terms = step_loss(self, inputs, layout, host_frames)
        self.opt.zero_grad(set_to_none=True)
        if self._device_skips:
            self._update_on_device(total)
        else:
            self._update_on_host(total)
        return terms

    def reposes(self, correctives: bool) -> bool:
        """Whether a step re-poses the bodies with the learned pose offsets (after warm-up)."""
        return self.corrections is not None and correctives and self.cfg.corrections.pose

    def _graph_refusal(self) -> str | None:
        """Why this trainer's steps cannot be captured (``TrainConfig.graph``), or None."""
        from uvatar.dva.raymarch import resolve_marcher

        c = self.cfg
        if self.device.type != "cuda":
            return "it needs CUDA"
        if resolve_marcher(c.raymarch.marcher) != "warp":
            return "it needs the Warp marcher (--marcher warp)"
        if self.ctx.active:
            return "not under torchrun (the processes average their gradients between backward and update)"
        if c.train.pairs_per_ray <= 0:
            return "it needs the marcher's fixed pair buffer (pairs_per_ray > 0)"
        if self.corrections is not None and c.corrections.pose and self.posing is None:
            return "the learned pose offsets re-pose the bodies on the host (pose_on_device=False)"
        shape = self.bank.fits.shape
        if shape is not None and len(shape) and bool((shape != shape[:1]).any()):
            return "the fits' body shapes differ between frames"
        return None

    @property
    def _device_skips(self) -> bool:
        """Whether a non-finite step is skipped on the device (CUDA, one process, fused Adam)."""
        return (self.device.type == "cuda" and not self.ctx.active
                and all(g.get("fused") for g in self.opt.param_groups))

    def _update_on_host(self, total) -> None:
        """Backward, clip and step, with the finiteness checks read on the host (a sync each on a GPU)."""
        learn = bool(total.requires_grad) and bool(torch.isfinite(total))
        if learn:
            total.backward()
        if self.ctx.active:
            learn = self._average_gradients(learn)
        if not total.requires_grad and not learn:  # no ray met a primitive (and correctives are off)
            pass
        elif learn:
            norm = torch.nn.utils.clip_grad_norm_(self.params, 1.0)
            if torch.isfinite(norm):
                self.opt.step()
            else:
                log.warning("step %d: non-finite gradient, update skipped", self.step)
        else:
            log.warning("step %d: non-finite loss, update skipped", self.step)

    def _update_on_device(self, total) -> None:
        """Backward, clip and step with no read-back: a non-finite loss gives non-finite gradients, hence
        a non-finite norm, and fused Adam skips the update wherever ``found_inf`` is 1 (moments and step
        count untouched), as the host path's skip does."""
        if not total.requires_grad:  # no ray met a primitive (and correctives are off)
            return
        total.backward()
        norm = torch.nn.utils.clip_grad_norm_(self.params, 1.0)
        found_inf = (~torch.isfinite(norm)).to(torch.float32)
        if not isinstance(self.skipped_updates, torch.Tensor):  # made at start where the update is on the
            self.skipped_updates = torch.zeros((), device=found_inf.device)  # device (a graph keeps it)
        self.skipped_updates.add_(found_inf)
        self.opt.found_inf = found_inf
        try:
            self.opt.step()
        finally:
            self.opt.found_inf = None

    def _report_skips(self) -> None:
        """Warn about the updates skipped on the device since the last report (called as terms are read)."""
        if not isinstance(self.skipped_updates, torch.Tensor):
            return
        n = int(self.skipped_updates)
        if n:
            log.warning("%d update(s) skipped before step %d: non-finite loss or gradient", n, self.step)
        self.skipped_updates.zero_()

    def _budget(self, rays: int):
        """The marcher's pair buffer for ``rays`` rays (``TrainConfig.pairs_per_ray``), or None (exact)."""
        per_ray = self.cfg.train.pairs_per_ray
        if per_ray <= 0:
            return None
        if self.budget is None:
            from uvatar.dva.raymarch_warp import PairBudget

            self.budget = PairBudget(1, self.device)
        self.budget.capacity = max(self.budget.capacity, math.ceil(per_ray * rays))
        return self.budget

    def _look_at_budget(self) -> None:
        """Report a step whose pairs overflowed the buffer (a step late on a GPU) and grow the buffer."""
        if self.budget is None:
            return
        needed = self.budget.poll()
        if self.budget.overflowed(needed):
            self.pair_overflows += 1
            new = math.ceil(needed * 1.25)
            log.warning("before step %d: the marcher's pair buffer held %d pairs, a step's render needed %d: that "
                        "step's render and gradients lost samples; the buffer now holds %d", self.step,
                        self.budget.capacity, needed, new)
            self.budget.capacity = new

    def _posing_on_device(self, body_given: bool, body_name: str, model_dir):
        """(body model, fits) on the training device for :meth:`_posed`'s device path, made once: the
        body is the trainer's own where it is on that device already, a registry body is asked for on
        the device (memoized there), a caller's body is copied there (the caller's stays where it is);
        the fits are the bank's (:class:`~uvatar.dva.corrections.FitParams`) without their shape, which
        stays on the host (a body's bind-state cache keys on it there, see :meth:`_posed`)."""
        from uvatar.devices import to_device_async

        dev = self.device
        here = self.body.device
        if here.type == dev.type and (here.index is None or dev.index is None or here.index == dev.index):
            body = self.body
        elif body_given:
            body = copy.deepcopy(self.body).to(dev)
        else:
            body = make_body(body_name, dev, model_dir)
        f = self.bank.fits
        fits = FitParams(*(to_device_async(x, dev) for x in (f.rotvecs, f.Rh, f.Th, f.scale)), shape=None)
        return body, fits

    def _posed(self, frames: torch.Tensor, device_frames: torch.Tensor | None = None):
        """(posed vertices (B, V, 3), joint rotvecs (B, J, 3)) of bank frames (B,) (host int64) re-posed
        with the learned pose offsets (a step after warm-up, :meth:`reposes`; before, the step takes the
        fits as they are from its inputs). Re-posing runs where ``pose_on_device`` says: on the device
        (:attr:`posing`: the body model and the fits there; the frames go over asynchronously, the shapes
        stay on the host; nothing is read back), or on the host (the body model as loaded, on the CPU:
        the offsets are read back, a sync each step on a GPU; the reference twin). ``device_frames``:
        ``frames`` already on the device (a captured step's input)."""
        from uvatar.devices import to_device_async

        fits = self.bank.fits
        shape = None if fits.shape is None else fits.shape[frames]
        if self.posing is not None:
            body, device_fits = self.posing
            on_device = device_frames if device_frames is not None else to_device_async(frames, self.device)
            return pose_corrected(body, self.corrections, device_fits, on_device, shape)
        rot, Rh, Th = self.corrections.pose_inputs(fits, frames, True)
        # the body model poses on the CPU: reading the offsets back is this step's one sync on a GPU
        verts = pose_vertices(self.body, rot.cpu(), Rh.cpu(), Th.cpu(), fits.scale[frames], shape)
        return verts.to(self.device), rot.to(self.device)  # differentiable: the offsets learn through it

    def _average_gradients(self, learned: bool) -> bool:
        """Average the gradients over the processes (one all-reduce of every gradient, zeros where
        this process has none, plus a has-gradient flag per parameter); a parameter no process has a
        gradient for keeps ``grad=None`` (Adam skips it, as in one process). True when any process
        learned something this step."""
        params = self.params
        flags = [float(p.grad is not None) for p in params] + [float(learned)]
        flat = torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in params]
                         + [torch.tensor(flags, dtype=params[0].dtype, device=self.device)])
        flat = all_sum(flat)
        flags = flat[-len(flags):].tolist()
        offset = 0
        for p, has in zip(params, flags, strict=False):
            n = p.numel()
            p.grad = flat[offset:offset + n].view_as(p) / self.ctx.world if has else None
            offset += n
        return flags[-1] > 0

    def set_lr(self, progress: float) -> float:
        """Learning rate for run progress in [0, 1] (exponential decay in the last part of the run)."""
        t = self.cfg.train
        frac = min(1.0, max(0.0, (progress - t.lr_decay_start) / max(1e-9, 1.0 - t.lr_decay_start)))
        decay = t.lr_final ** frac
        lr = t.lr * decay
        bases = [t.lr, self.cfg.corrections.lr]  # the model's group, then the corrections'
        for group, base in zip(self.opt.param_groups, bases, strict=False):
            if isinstance(group["lr"], torch.Tensor):  # a captured step's: written in place, read on the device
                group["lr"].fill_(base * decay)
            else:
                group["lr"] = base * decay
        return lr

    def save(self, seconds: float) -> None:
        """Checkpoint (rank 0) with the clock: sampling RNG, torch RNG and ``seconds`` trained."""
        if self.ctx.is_main:
            clock = {"rng": self.rng.getstate(), "torch_rng": torch.get_rng_state(), "seconds": seconds}
            save_checkpoint(self.out / CHECKPOINT, self.model, self.opt, self.step, self.meta, clock,
                            self.corrections)

    def run(self, iters: int | None = None, minutes: float | None = None) -> dict:
        from torch.utils.tensorboard import SummaryWriter
        from tqdm import tqdm

        t = self.cfg.train
        iters = t.iters if iters is None else iters
        minutes = t.minutes if minutes is None else minutes
        writer = SummaryWriter(str(self.out / "tb")) if self.ctx.is_main else None
        start, last = time.time() - self.seconds, {}  # the time budget counts earlier parts of the run
        inside: list[float] = []   # the logged steps' opacity inside the masks (crops showing the person)
        bar = tqdm(total=iters, initial=min(self.step, iters), desc="train dva", disable=not self.progress)

        def elapsed() -> float:  # rank 0's clock for every rank: all stop at the same step
            t_ = torch.tensor([time.time() - start], dtype=torch.float64)
            if self.ctx.active:
                torch.distributed.broadcast(t_, 0)
            return float(t_[0])

        try:
            while self.step < iters and (seconds := elapsed()) < minutes * 60:
                progress = max(self.step / max(iters, 1), seconds / max(minutes * 60, 1e-9))
                self.set_lr(progress)
                last = self.train_step()
                bar.update(1)
                if self.step % 10 == 0 or self.step == 1:  # the terms are read (one sync) only when logged
                    if writer is not None:
                        for k, v in last.items():
                            writer.add_scalar(f"loss/{k}", v, self.step)
                    bar.set_postfix(loss=f"{last['total']:.4f}", psnr=f"{last['psnr']:.1f}")
                    if last.get("mask_fraction", 0.0) > 0.05:
                        inside.append(last["opacity_in_mask"])
                if self.step % t.checkpoint_every == 0:
                    self.save(elapsed())
        finally:
            bar.close()
            if writer is not None:
                writer.close()
        self.save(elapsed())
        self.ctx.barrier()
        summary = {"steps": self.step, "seconds": round(time.time() - start, 1), "last": dict(last),
                   "frames": len(self.bank), "skipped_frames": self.bank.skipped,
                   "corrections": self.corrections.summary() if self.corrections is not None else None, **{
                       k: self.meta[k] for k in ("train_cameras", "perceptual", "body_model", "seed")}}
        summary.update(_emptiness(inside[-20:], self.step))
        if self.ctx.is_main:
            write_json(self.out / "run.json", {"config": self.cfg.to_dict(), "summary": summary})
        return summary


def _emptiness(inside: list[float], step: int) -> dict:
    """The summary's ``opacity_in_mask`` (the mean of the last logged steps' opacity inside the persons'
    masks, None when none was logged) and ``empty`` (below :data:`~uvatar.dva.losses.EMPTY_OPACITY`: the
    avatar renders no person, said in a warning)."""
    if not inside:
        return {"opacity_in_mask": None, "empty": None}
    mean = float(np.mean(inside))
    empty = mean < EMPTY_OPACITY
    if empty:
        log.warning("the avatar is empty at step %d: its opacity inside the person's masks averaged %.3f over "
                    "its last logged steps (a healthy run: ~0.8); it renders no person. Train it again with "
                    "another --seed (and --loss-beta-outside-mask, the default, if it was off)", step, mean)
    return {"opacity_in_mask": round(mean, 4), "empty": empty}


def train_dva(source, out_dir, cfg: DvaConfig, iters=None, minutes=None, device="cpu", resume=False,
              body=None, vgg_weights=None, progress=True, body_model=None, model_dir=None, seed: int = 0) -> dict:
    """Train (or resume) a DVA run in ``out_dir``; returns a summary dict (also in run.json).
    ``body_model`` ("anny", "smpl", "smplx"; default: the source's) and ``model_dir`` (SMPL files)
    pick the body model on any layout. Under torchrun the processes share each global batch (see the
    module docstring). ``seed``: initial weights and the sampling of frames, cameras and crops (a
    resumed run continues its checkpoint's sampling state)."""
    with distributed_context(device) as ctx:
        trainer = Trainer(source, out_dir, cfg, body=body, device=ctx.device, vgg_weights=vgg_weights,
                          resume=resume, seed=seed, progress=progress, body_model=body_model, model_dir=model_dir, ctx=ctx)
        return trainer.run(iters, minutes)


def _tupled(state):
    """random.Random state as ``setstate`` wants it (tuples; torch.save may hand back lists)."""
    return tuple(_tupled(x) for x in state) if isinstance(state, (list, tuple)) else state
