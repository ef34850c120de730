"""Train a DVA avatar on a multi-view source (``uvatar train dva``).

Each step draws ``batch`` random (frame, training camera) pairs, renders a random ``patch`` x ``patch``
crop around the person in that camera and fits it (losses in :mod:`uvatar.dva.losses`). Image features
follow the paper's two-stage curriculum: for the first ``all_views_iters`` steps they come from every
training view, afterwards from ``driving_views`` (3) random training views. Primitive correctives are off
for the first ``warmup_iters`` steps. The run folder holds ``checkpoint.pt`` (written atomically every
``checkpoint_every`` steps and at the end; ``resume=True`` continues from it), ``run.json`` and
TensorBoard logs in ``tb/``.
"""

from __future__ import annotations

import logging
import random
import time
from pathlib import Path

import numpy as np
import torch

from uvatar.dva.dataset import FrameBank
from uvatar.dva.losses import DvaLoss, Vgg19Features
from uvatar.dva.model import DvaConfig, DvaModel, pixel_rays
from uvatar.errors import InputError
from uvatar.io_utils import atomic_path, sweep_partial_writes, write_json

log = logging.getLogger(__name__)
CHECKPOINT = "checkpoint.pt"


def make_body(name: str, device="cpu"):
    """The body model a run was trained with ("toy" is the test tube of :mod:`uvatar.dva.toy`)."""
    if name == "toy":
        from uvatar.dva.toy import ToyBody

        return ToyBody()
    from uvatar.body.registry import load_body_model

    return load_body_model(name, device=device)


def patch_pixels(mask: np.ndarray, size: int, rng: random.Random) -> np.ndarray:
    """(size*size, 2) integer (x, y) pixels of a square crop whose centre lies in the mask's bounding
    box (grown by half a patch), clipped to the image."""
    H, W = mask.shape
    size = min(size, H, W)
    ys, xs = np.nonzero(mask)
    if ys.size:
        cy = rng.randint(int(ys.min()), int(ys.max()))
        cx = rng.randint(int(xs.min()), int(xs.max()))
    else:
        cy, cx = rng.randrange(H), rng.randrange(W)
    y0 = int(np.clip(cy - size // 2, 0, H - size))
    x0 = int(np.clip(cx - size // 2, 0, W - size))
    yy, xx = np.mgrid[y0:y0 + size, x0:x0 + size]
    return np.stack([xx.ravel(), yy.ravel()], 1)


def save_checkpoint(path: Path, model, optimizer, step: int, meta: dict) -> None:
    state = {"model": model.state_dict(), "optimizer": optimizer.state_dict() if optimizer else None,
             "step": step, "config": model.cfg.to_dict(), "meta": meta}
    with atomic_path(path, suffix=".pt") as tmp:
        torch.save(state, tmp)


def load_run(run_dir, device="cpu"):
    """(model, body, meta, step) from a run folder's checkpoint."""
    path = Path(run_dir) / CHECKPOINT
    if not path.is_file():
        raise InputError(path, "no DVA checkpoint here (train with `uvatar train dva` first)")
    try:
        state = torch.load(path, map_location=device, weights_only=False)
        cfg = DvaConfig.from_dict(state["config"])
        meta = state["meta"]
    except Exception as exc:  # noqa: BLE001 - any unreadable checkpoint is the same user error
        raise InputError(path, f"unreadable checkpoint ({exc.__class__.__name__}: {exc})") from None
    body = make_body(meta["body_model"], device)
    model = DvaModel(cfg, body.template, meta["conditioning_joints"]).to(device)
    model.load_state_dict(state["model"])
    model.eval()
    return model, body, meta, state["step"]


class Trainer:
    """Holds the model, the data bank and the optimizer; ``run()`` trains until iters or minutes."""

    def __init__(self, source, out_dir, cfg: DvaConfig, body=None, device="cpu", vgg_weights=None,
                 resume=False, seed=0, progress=True):
        self.source, self.out = source, Path(out_dir)
        self.device, self.progress = torch.device(device), progress
        self.rng = random.Random(seed)
        torch.manual_seed(seed)
        self.out.mkdir(parents=True, exist_ok=True)
        sweep_partial_writes(self.out)  # temp files of writes a kill cut short
        ckpt = self.out / CHECKPOINT
        state = None
        if resume and ckpt.is_file():
            state = torch.load(ckpt, map_location=self.device, weights_only=False)
            cfg = DvaConfig.from_dict(state["config"])  # the run's own config wins on resume
            log.info("resuming from %s at step %d", ckpt, state["step"])
        self.cfg = cfg
        body_name = getattr(body, "name", None) or source.body_model
        self.body = body if body is not None else make_body(body_name, "cpu")
        joints = tuple(getattr(self.body, "conditioning_joints", range(self.body.num_joints)))
        self.model = DvaModel(cfg, self.body.template, joints).to(self.device)
        self.bank = FrameBank(source, self.body, self.model.image_raster, self.body.template,
                              source.train_frames, source.train_cameras, progress)
        vgg = Vgg19Features.from_file(vgg_weights).to(self.device) if vgg_weights else None
        self.loss = DvaLoss(cfg.loss, vgg).to(self.device)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=cfg.train.lr)
        self.step = 0
        self.meta = {"body_model": body_name, "conditioning_joints": list(joints),
                     "source": str(getattr(source, "root", "")), "train_cameras": list(source.train_cameras),
                     "train_frames": list(self.bank.frames), "skipped_frames": self.bank.skipped,
                     "backgrounds": {c: self.bank.backgrounds[i].tolist() for i, c in enumerate(self.bank.cameras)},
                     "perceptual": "vgg19" if vgg else "ssim", "protocol": source.protocol}
        if state is not None:
            self.model.load_state_dict(state["model"])
            if state.get("optimizer"):
                self.opt.load_state_dict(state["optimizer"])
            self.step = int(state["step"])

    def sample(self):
        """One batch: (frame indices, camera indices, image textures (B,4,R,R))."""
        t = self.cfg.train
        n_cam = len(self.bank.cameras)
        frames = [self.rng.randrange(len(self.bank)) for _ in range(t.batch)]
        cams = [self.rng.randrange(n_cam) for _ in range(t.batch)]
        if self.step < t.all_views_iters:
            views = [list(range(n_cam))] * t.batch
        else:
            views = [self.rng.sample(range(n_cam), min(t.driving_views, n_cam)) for _ in range(t.batch)]
        tex = torch.stack([self.bank.image_texture(f, v) for f, v in zip(frames, views, strict=False)])
        return frames, cams, tex.to(self.device)

    def train_step(self) -> dict:
        t = self.cfg.train
        self.model.correctives_on.fill_(self.step >= t.warmup_iters)
        frames, cams, tex = self.sample()
        fi = torch.tensor(frames)
        centers = torch.as_tensor(np.stack([self.bank.cams[c].center for c in cams]), dtype=torch.float32)
        out = self.model(self.bank.vertices[fi].to(self.device), self.bank.rotvecs[fi].to(self.device), tex,
                         centers.to(self.device))
        preds, targets, alphas, masks = [], [], [], []
        for b, (f, c) in enumerate(zip(frames, cams, strict=False)):
            mask = self.bank.masks[f][c]
            pix = patch_pixels(mask, t.patch, self.rng)
            o, d = pixel_rays(self.bank.cams[c], pix, self.device)
            bg = torch.as_tensor(self.bank.backgrounds[c], device=self.device)
            rgb, alpha = self.model.render_rays(out, b, o, d, bg, camera=self.bank.cams[c], pixels=pix)
            P = int(round(np.sqrt(pix.shape[0])))
            img = self.bank.images[f][c][pix[:, 1], pix[:, 0]].astype(np.float32) / 255.0
            preds.append(rgb.T.reshape(3, P, P))
            targets.append(torch.as_tensor(img, device=self.device).T.reshape(3, P, P))
            alphas.append(alpha.reshape(P, P))
            masks.append(torch.as_tensor(mask[pix[:, 1], pix[:, 0]], dtype=torch.float32,
                                         device=self.device).reshape(P, P))
        total, terms = self.loss(torch.stack(preds), torch.stack(targets), torch.stack(alphas),
                                 torch.stack(masks), out.scales, self.model.rest_scales)
        self.opt.zero_grad(set_to_none=True)
        if not total.requires_grad:  # no ray met a primitive (and correctives are off): nothing to learn
            pass
        elif torch.isfinite(total):
            total.backward()
            norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), 1.0)
            if torch.isfinite(norm):
                self.opt.step()
            else:
                log.warning("step %d: non-finite gradient, update skipped", self.step)
        else:
            log.warning("step %d: non-finite loss, update skipped", self.step)
        self.step += 1
        terms["total"] = float(total.detach())
        mse = float(((torch.stack(preds) - torch.stack(targets)) ** 2).mean().detach())
        terms["psnr"] = float(-10 * np.log10(max(mse, 1e-10)))
        return terms

    def set_lr(self, progress: float) -> float:
        """Learning rate for run progress in [0, 1] (exponential decay in the last part of the run)."""
        t = self.cfg.train
        frac = min(1.0, max(0.0, (progress - t.lr_decay_start) / max(1e-9, 1.0 - t.lr_decay_start)))
        lr = t.lr * t.lr_final ** frac
        for group in self.opt.param_groups:
            group["lr"] = lr
        return lr

    def save(self):
        save_checkpoint(self.out / CHECKPOINT, self.model, self.opt, self.step, self.meta)

    def run(self, iters: int | None = None, minutes: float | None = None) -> dict:
        from torch.utils.tensorboard import SummaryWriter
        from tqdm import tqdm

        t = self.cfg.train
        iters = t.iters if iters is None else iters
        minutes = t.minutes if minutes is None else minutes
        writer = SummaryWriter(str(self.out / "tb"))
        start, last = time.time(), {}
        bar = tqdm(total=iters, initial=min(self.step, iters), desc="train dva", disable=not self.progress)
        try:
            while self.step < iters and (time.time() - start) < minutes * 60:
                progress = max(self.step / max(iters, 1), (time.time() - start) / max(minutes * 60, 1e-9))
                self.set_lr(progress)
                last = self.train_step()
                if self.step % 10 == 0 or self.step == 1:
                    for k, v in last.items():
                        writer.add_scalar(f"loss/{k}", v, self.step)
                bar.update(1)
                bar.set_postfix(loss=f"{last['total']:.4f}", psnr=f"{last['psnr']:.1f}")
                if self.step % t.checkpoint_every == 0:
                    self.save()
        finally:
            bar.close()
            writer.close()
        self.save()
        summary = {"steps": self.step, "seconds": round(time.time() - start, 1), "last": last,
                   "frames": len(self.bank), "skipped_frames": self.bank.skipped, **{
                       k: self.meta[k] for k in ("train_cameras", "perceptual", "body_model")}}
        write_json(self.out / "run.json", {"config": self.cfg.to_dict(), "summary": summary})
        return summary


def train_dva(source, out_dir, cfg: DvaConfig, iters=None, minutes=None, device="cpu", resume=False,
              body=None, vgg_weights=None, progress=True) -> dict:
    """Train (or resume) a DVA run in ``out_dir``; returns a summary dict (also in run.json)."""
    trainer = Trainer(source, out_dir, cfg, body=body, device=device, vgg_weights=vgg_weights,
                      resume=resume, progress=progress)
    return trainer.run(iters, minutes)
