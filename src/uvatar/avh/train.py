"""Train the AVH generator on a baked dataset (paper §3.3, §4.2): ``uvatar train avh BAKED RUN``.

Adam (lr 1.31e-3), batch 8, ExponentialLR γ = 0.99 per epoch, loss of :mod:`uvatar.avh.loss`.
On CUDA: bf16 autocast and channels_last. Train maps are resampled to the model's output resolution.
Displacements are learned in ``TrainConfig.displacement_frame`` (default the rest frame, see
:mod:`uvatar.avh.displacement_frame`); run.json records which.

Run folder layout::

    RUN/run.json        model config, train config, baked path, body model + shape, conditioning joints,
                        train/val frames, parameter count
    RUN/checkpoint.pt   latest epoch (model, optimizer, scheduler, history); written atomically each epoch
    RUN/model.pt        weights of the latest epoch (their moving average with ``ema_decay``) + config
                        (what `uvatar export` reads)
    RUN/history.json    per-epoch losses
    RUN/done.json       summary written when all epochs are done
    RUN/tb/             TensorBoard scalars (loss, lr) and preview images
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from uvatar.avh.bake.dataset import read_dataset_info
from uvatar.avh.data import BakedFrames, body_model_info, load_baked_frames, selection
from uvatar.avh.displacement_frame import DISPLACEMENT_FRAMES, DISPLACEMENT_SPACES, displacements_to_frame
from uvatar.avh.ema import WeightAverage
from uvatar.avh.loss import DISPLACEMENT_WEIGHTINGS, avh_loss, displacement_mask, texture_weight
from uvatar.avh.model import (
    AvhConfig,
    AvhGenerator,
    count_parameters,
    encode_pose,
    init_output_bias,
    root_joint,
    select_conditioning_angles,
    with_orientation,
)
from uvatar.distributed import DistContext, all_sum, distributed_context, global_batchnorm, local_share
from uvatar.errors import InputError, UvatarError, check_values
from uvatar.io_utils import atomic_path, check_output_location, read_json, sweep_partial_writes, write_json

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainConfig:
    """Optimization settings (paper defaults). ``displacement_weight`` scales the displacement term.
    ``displacement_frame``: "rest" (baked body-frame maps are unposed by each texel's blended skinning
    rotation before training; needs a body model, else falls back to "body") or "body" (as baked).
    ``shading_lr_scale``: the shading head's learning rate is ``lr`` times this (a studio-orientation
    texel generator). On the demo's lit studio 10x and 30x let the head learn more of the light (its
    shading spread 0.05 -> 0.08) but did not lower the held-out error (docs/results.md), so it is 1.
    ``ema_decay``: the validated, saved and exported weights are an exponential moving average of the
    trained ones with this decay per step (:mod:`uvatar.avh.ema`); 0: the last step's weights.
    ``calibrate_lights``: before the first step, a generator with a light rig gets its lights, per-texel
    ambient and shares, and its texture bias (an albedo) fitted to all training frames at once, this
    many steps of 16 frames (:func:`uvatar.avh.lights.calibrate_rig`; 0: the rig starts unlit, as before).
    ``fit_displacement_gain``: after the last epoch, the saved weights' pose-dependent displacement is
    scaled by the gain in [0, 1] with the lowest validation displacement loss
    (:func:`fit_displacement_gain`; needs validation frames; the checkpoint keeps the trained weights).
    With an output bias the residual is shrunk about its mean over the training frames (folded into the
    bias), so the gain changes the pose-dependent part only, not the mean map.
    ``recentre_displacement``: after the last epoch (before the gain), the saved weights' per-texel
    displacement output bias is reset so that the generator's mean displacement over the training
    frames is the plain mean of their kept texels (valid, inlier, w > 0; :func:`recentre_displacement`)
    instead of the w-weighted mean that training converges to: the eval's R² reference. Needs the
    output bias (the CPU presets).
    ``displacement_weighting``: "visibility" (the paper's: each texel's displacement error weighted by
    the bake's visibility w) or "uniform" (every kept texel, w > 0, once: the loss-optimal constant map is
    the plain mean of the kept texels, the eval's R² reference; :func:`uvatar.avh.loss.displacement_mask`)."""

    epochs: int = 500
    batch_size: int = 8
    lr: float = 1.31e-3
    lr_gamma: float = 0.99
    outlier_threshold: float = 0.05
    displacement_weight: float = 1.0
    device: str = "cpu"
    seed: int = 0
    preview_every: int = 10
    displacement_frame: str = "rest"
    pose_noise: float = 0.0
    shading_lr_scale: float = 1.0
    ema_decay: float = 0.0
    calibrate_lights: int = 600
    fit_displacement_gain: bool = False
    recentre_displacement: bool = False
    displacement_weighting: str = "visibility"
    tensorboard: bool = True
    progress: bool = True

    def __post_init__(self) -> None:
        checks = [(self.epochs >= 1, f"epochs must be >= 1, got {self.epochs}"),
                  (self.batch_size >= 1, f"batch size must be >= 1, got {self.batch_size}"),
                  (self.lr > 0, f"learning rate must be > 0, got {self.lr}"),
                  (0 < self.lr_gamma <= 1, f"learning-rate decay gamma must be in (0, 1], got {self.lr_gamma}"),
                  (self.displacement_weight >= 0, f"displacement weight must be >= 0, got {self.displacement_weight}"),
                  (self.pose_noise >= 0, f"pose noise must be >= 0, got {self.pose_noise}"),
                  (0 <= self.ema_decay < 1, f"ema decay must be in [0, 1), got {self.ema_decay}"),
                  (self.calibrate_lights >= 0, f"calibrate_lights must be >= 0 steps, got {self.calibrate_lights}"),
                  (self.shading_lr_scale > 0, f"shading learning-rate scale must be > 0, got {self.shading_lr_scale}"),
                  (self.displacement_weighting in DISPLACEMENT_WEIGHTINGS,
                   f"displacement weighting must be one of {DISPLACEMENT_WEIGHTINGS}, "
                   f"got {self.displacement_weighting!r}"),
                  (self.displacement_frame in DISPLACEMENT_FRAMES,
                   f"displacement frame must be one of {DISPLACEMENT_FRAMES}, got {self.displacement_frame!r}")]
        check_values(checks)


@dataclass
class TrainingData:
    """Training tensors on the device: conditioning angles (N, 3·J_c) radians and maps (N, C, R, R)."""

    names: list[str]
    pose_angles: torch.Tensor
    maps: dict[str, torch.Tensor]

    def batch(self, idx: torch.Tensor, pose_noise: float = 0.0) -> tuple[tuple[torch.Tensor, torch.Tensor],
                                                                          dict[str, torch.Tensor]]:
        """((encoded poses (B, 6·J_c), angles (B, 3·J_c)), maps) of frames ``idx``: the generator's
        inputs and targets; ``pose_noise``: std (radians) of Gaussian noise added to the angles before
        encoding (augmentation; 0 = none)."""
        angles = self.pose_angles[idx]
        if pose_noise > 0:
            angles = angles + pose_noise * torch.randn_like(angles)
        return (encode_pose(angles), angles), {k: v[idx] for k, v in self.maps.items()}

    def __len__(self) -> int:
        return len(self.names)


def to_training_data(frames: BakedFrames, conditioning_joints, device: str | torch.device,
                     orientation_root: int | None = None) -> TrainingData:
    """BakedFrames (numpy, HWC) -> TrainingData (torch, BCHW, on ``device``). ``orientation_root``: the
    root joint whose slot carries each frame's Rh (a ``orientation="studio"`` generator), else None."""
    def chw(a):
        t = torch.from_numpy(np.ascontiguousarray(a))
        return (t.permute(0, 3, 1, 2) if t.ndim == 4 else t[:, None]).contiguous().to(device)

    poses = torch.from_numpy(frames.poses)
    if orientation_root is not None:
        poses = with_orientation(poses, torch.from_numpy(np.asarray(frames.Rh, np.float32)), orientation_root)
    angles = select_conditioning_angles(poses, conditioning_joints)
    maps = {"texture": chw(frames.texture), "displacement": chw(frames.displacement),
            "kappa": chw(frames.kappa), "w": chw(frames.w), "valid": chw(frames.valid.astype(np.float32))}
    return TrainingData(frames.names, angles.float().to(device), maps)


def parameter_groups(model: torch.nn.Module, cfg: TrainConfig) -> list[dict]:
    """Adam's parameter groups: the shading head (if any) at ``lr · shading_lr_scale``, the rest at ``lr``
    (names may carry DDP's ``module.`` prefix)."""
    shading, rest = [], []
    for name, param in model.named_parameters():
        (shading if ".shading." in f".{name}" else rest).append(param)
    groups = [{"params": rest}]
    if shading:
        groups.append({"params": shading, "lr": cfg.lr * cfg.shading_lr_scale})
    return groups


def mean_maps(data: TrainingData, excluded, outlier_threshold: float,
              displacement_weighting: str = "visibility") -> tuple[torch.Tensor, torch.Tensor]:
    """Loss-weighted mean texture and displacement (3, R, R) over ``data`` (plain mean where unweighted;
    ``displacement_weighting``: the loss's, :func:`uvatar.avh.loss.displacement_mask`)."""
    m = data.maps
    wt = texture_weight(m)
    tex = (wt * m["texture"]).sum(0) / wt.sum(0).clamp_min(1e-6)
    tex = torch.where(wt.sum(0) > 1e-6, tex, m["texture"].mean(0))
    wd = displacement_mask(m["displacement"], m["w"], m["valid"], excluded, outlier_threshold, displacement_weighting)
    disp = (wd * m["displacement"]).sum(0) / wd.sum(0).clamp_min(1e-6)
    return tex, torch.where(wd.sum(0) > 1e-6, disp, torch.zeros_like(disp))


def resolve_body(meta: dict, resolution: int, body=None, baked_dir: Path | None = None):
    """(conditioning joint indices, fingers/toes mask (R, R) bool or None, joint names or None, body or None).

    Uses ``body`` when given, otherwise loads the dataset's body model; ``dataset.json`` may also list
    ``conditioning_joints`` (used as is, e.g. by test fixtures whose body model is "none").
    """
    name, _ = body_model_info(meta)
    if body is None and name != "none":
        from uvatar.body import load_body_model

        try:
            body = load_body_model(name)
        except ValueError as exc:  # a name no backend has: the dataset's, not a traceback
            raise InputError(Path(baked_dir or ".") / "dataset.json", str(exc)) from None
    if body is None:
        if "conditioning_joints" not in meta:
            raise InputError(Path(baked_dir or ".") / "dataset.json",
                             "body model 'none' needs a conditioning_joints list")
        log.warning("no body model: fingers/toes are not left out of the displacement loss")
        return [int(j) for j in meta["conditioning_joints"]], None, meta.get("joint_names"), None
    from uvatar.body import part_masks

    cond = [int(j) for j in meta.get("conditioning_joints", body.conditioning_joints)]
    excluded = np.asarray(part_masks(body, resolution)["fingers_toes"], bool)
    return cond, excluded, list(body.joint_names), body



def _load_checkpoint(path: Path) -> dict:
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any unreadable checkpoint is a user-facing input error
        raise InputError(path, f"cannot read checkpoint ({exc})") from exc


def _save(path: Path, obj) -> None:
    with atomic_path(path, suffix=".pt") as tmp:
        torch.save(obj, tmp)


def _preview(model: AvhGenerator, data: TrainingData) -> np.ndarray:
    """(3, R, 4R) image: predicted texture | target texture | predicted |d| | target |d| of the first frame."""
    pose, batch = data.batch(torch.tensor([0], device=data.pose_angles.device))
    with torch.no_grad():
        tex, disp = model(*pose)
    scale = model.config.displacement_scale

    def mag(d):
        return (d.float().norm(dim=1, keepdim=True) / scale).clamp(0, 1).expand(-1, 3, -1, -1)

    row = torch.cat([tex.float(), batch["texture"], mag(disp), mag(batch["displacement"])], dim=3)
    return row[0].clamp(0, 1).cpu().numpy()


def evaluate_loss(model: AvhGenerator, data: TrainingData, excluded, cfg: TrainConfig) -> tuple[float, float, float]:
    """Mean (total, texture, displacement) loss over ``data`` in eval mode (no gradients)."""
    model.eval()
    sums = np.zeros(3)
    with torch.no_grad():
        for start in range(0, len(data), cfg.batch_size):
            idx = torch.arange(start, min(start + cfg.batch_size, len(data)), device=data.pose_angles.device)
            pose, batch = data.batch(idx)
            tex, disp = model(*pose)
            losses = avh_loss(tex, disp, batch, excluded, cfg.outlier_threshold, cfg.displacement_weight,
                              displacement_weighting=cfg.displacement_weighting)
            sums += np.array([float(x) for x in losses]) * len(idx)
    return tuple(float(x) for x in sums / max(len(data), 1))


def displacement_residual_mean(model: AvhGenerator, data: TrainingData, batch_size: int = 8) -> torch.Tensor:
    """(1, 3, R, R): the displacement decoder's pose-dependent output (before its per-texel output bias
    and the tanh) averaged over the frames of ``data``, in eval mode."""
    model.eval()
    total = None
    with torch.no_grad():
        for start in range(0, len(data), batch_size):
            idx = torch.arange(start, min(start + batch_size, len(data)), device=data.pose_angles.device)
            (encoded, angles), _ = data.batch(idx)
            dec = model.displacement_decoder
            pose_map = model.texel_pose(angles) if model.texel_pose is not None else None
            out = dec(model.cuboid(encoded), pose_map)
            if dec.bias is not None:
                out = out - dec.bias
            part = out.float().sum(0, keepdim=True)
            total = part if total is None else total + part
    return total / max(len(data), 1)


def scale_displacement_residual(model: AvhGenerator, gain: float, center: torch.Tensor | None = None) -> None:
    """Multiply the displacement decoder's pose-dependent output (its last layer; the per-texel output
    bias is kept) by ``gain``, in place. ``center`` (1, 3, R, R), the output's mean over the training
    frames (:func:`displacement_residual_mean`; needs the output bias): the output is shrunk about it
    instead of about 0, ``(1 - gain) · center`` is added to the output bias, so the mean over those
    frames stays and only its pose-dependent variation is scaled."""
    dec = model.displacement_decoder
    final = dec.net[-1]
    with torch.no_grad():
        final.weight.mul_(gain)
        final.bias.mul_(gain)
        if center is not None:
            if dec.bias is None:
                raise ValueError("shrinking about the mean output needs the decoder's output bias")
            dec.bias.add_((1.0 - gain) * center.to(dec.bias))


def recentre_displacement(model: AvhGenerator, center: torch.Tensor, mean_map: torch.Tensor) -> None:
    """Set the displacement decoder's per-texel output bias so that its output's mean over the training
    frames, ``center`` + bias (:func:`displacement_residual_mean`), is ``mean_map`` (3, R, R) metres
    (through the tanh, as :func:`uvatar.avh.model.init_output_bias`), in place; the pose-dependent
    variation about that mean is unchanged. Needs the output bias."""
    dec = model.displacement_decoder
    if dec.bias is None:
        raise ValueError("recentring the displacement needs the decoder's output bias")
    target = torch.atanh((mean_map.float() / model.config.displacement_scale).clamp(-0.98, 0.98))[None]
    with torch.no_grad():
        dec.bias.copy_(target.to(dec.bias) - center.to(dec.bias))


def fit_displacement_gain(model: AvhGenerator, data: TrainingData, excluded, cfg: TrainConfig,
                          steps: int = 20, center: torch.Tensor | None = None) -> tuple[float, list[float]]:
    """(gain, displacement loss per gain): the gain in [0, 1] (``steps`` + 1 values) of the
    displacement decoder's pose-dependent output (:func:`scale_displacement_residual`, about ``center``)
    with the lowest displacement loss on ``data`` (the validation frames). Gain 0 is the mean map alone,
    1 the generator as trained: where the baked displacements vary with more than the pose (noise,
    the fingers' articulation), the generator's residual fitted to the training frames is only partly
    right on other frames, and the loss-optimal shrinkage keeps the part that is. ``model`` is left
    as it was."""
    import copy

    losses = []
    for k in range(steps + 1):
        trial = copy.deepcopy(model)
        scale_displacement_residual(trial, k / steps, center)
        losses.append(evaluate_loss(trial, data, excluded, cfg)[2])
    return float(np.argmin(losses)) / steps, losses


def train_avh(baked_dir: str | Path, run_dir: str | Path, model_config: AvhConfig,
              train_config: TrainConfig = TrainConfig(), resume: bool = False, body=None,
              preset_name: str | None = None) -> dict:
    """Train (or resume) and return a summary dict (epochs, losses, parameters, seconds, samples/s).

    ``model_config.num_pose_joints`` is replaced by the number of conditioning joints of the body.
    Raises UvatarError if ``run_dir`` holds a checkpoint and ``resume`` is False.

    Under ``torchrun`` (:mod:`uvatar.distributed`) each of the N processes trains on ``batch_size / N``
    samples of every global batch (DistributedSampler order, the same alone or not), DDP averages the
    gradients and BatchNorm and the loss use global-batch sums, so the steps are those of one process;
    rank 0 alone logs and writes the run folder. A checkpoint resumes under any number of processes.
    """
    with distributed_context(train_config.device) as ctx:
        return _train_avh(ctx, Path(baked_dir), Path(run_dir), model_config, train_config, resume, body,
                          preset_name)


def _epoch_order(n: int, epoch: int, cfg: TrainConfig) -> list[int]:
    """The epoch's frame order, the same in every process: DistributedSampler's seeded shuffle
    (seed + epoch) over the whole set. Global batch s is ``order[s·B:(s+1)·B]`` for any number of
    processes; rank r takes every world-th of it (:func:`uvatar.distributed.local_share`), so there is
    no padding and no frame counted twice, whatever the frame count."""
    from torch.utils.data import DistributedSampler

    sampler = DistributedSampler(range(n), num_replicas=1, rank=0, shuffle=True, seed=cfg.seed)
    sampler.set_epoch(epoch)
    return list(sampler)


def _train_avh(ctx: DistContext, baked_dir: Path, run_dir: Path, model_config: AvhConfig, cfg: TrainConfig,
               resume: bool, body, preset_name: str | None) -> dict:
    from tqdm import tqdm

    if cfg.batch_size % ctx.world:
        raise UvatarError(f"batch size {cfg.batch_size} is not divisible by the {ctx.world} processes "
                          "(the batch size is the global batch)")
    local_batch = cfg.batch_size // ctx.world
    ckpt_path = run_dir / "checkpoint.pt"
    check_output_location(ckpt_path)  # before loading the data
    sweep_partial_writes(run_dir)  # temp files of checkpoint writes a kill cut short
    state = None
    has_checkpoint = ckpt_path.exists()
    ctx.barrier()  # every rank has looked before rank 0 writes anything
    if has_checkpoint:
        if not resume:
            raise UvatarError(f"{run_dir}: holds a checkpoint; resume=True continues it, or pick a new folder")
        state = _load_checkpoint(ckpt_path)
        saved = AvhConfig(**state["model_config"])
        if (saved.feature_size, saved.latent, saved.resolution) != (model_config.feature_size, model_config.latent,
                                                                    model_config.resolution):
            log.warning("resuming %s with its checkpoint's model (f_c=%d, latent=%d, %d texels), not the one asked for",
                        run_dir, saved.feature_size, saved.latent, saved.resolution)
        model_config = saved
    meta = read_dataset_info(baked_dir, required=True)
    train_names, val_names = selection(meta, baked_dir)
    R = model_config.resolution
    cond, excluded_np, joint_names, body = resolve_body(meta, R, body, baked_dir)
    root = None
    if model_config.orientation == "studio":  # the root's slot carries Rh: one more conditioning "joint"
        if body is None:
            raise InputError(baked_dir / "dataset.json", "orientation 'studio' needs the body model's skeleton; "
                                                         "this dataset has body model 'none'")
        root = root_joint(body.template.joint_parents)
        cond = [*[j for j in cond if j != root], root]
    model_config = replace(model_config, num_pose_joints=len(cond))
    if state is not None:
        cfg = replace(cfg, displacement_frame=state.get("train_config", {}).get("displacement_frame", "body"))
    if cfg.displacement_frame == "rest" and body is None:
        log.warning("no body model: displacements are learned in the body frame, not the rest frame")
        cfg = replace(cfg, displacement_frame="body")
    _, shapes = body_model_info(meta)

    device = ctx.device
    if device.type == "cuda" and not torch.cuda.is_available():
        raise UvatarError("device 'cuda' requested but CUDA is not available")
    torch.manual_seed(cfg.seed)
    def load(names, progress=False):
        frames = load_baked_frames(baked_dir, names, R, progress,
                                   None if body is None else 3 * body.num_joints)
        if max(cond, default=-1) >= frames.poses.shape[1] // 3:
            raise InputError(baked_dir / "dataset.json", f"conditioning joint {max(cond)} is not in the "
                             f"frames' poses ({frames.poses.shape[1] // 3} joints)")
        return to_training_data(displacements_to_frame(frames, cfg.displacement_frame, body, shapes), cond, device,
                                root)

    train = load(train_names, cfg.progress and ctx.is_main)
    val = load(val_names) if val_names else None
    excluded = None if excluded_np is None else torch.from_numpy(excluded_np).to(device)

    model = AvhGenerator(model_config)
    if model.texel_pose is not None:
        if body is None:
            raise InputError(baked_dir / "dataset.json", "texel conditioning needs the body model's skinning "
                                                         "weights; this dataset has body model 'none'")
        from uvatar.avh.texel_pose import (
            conditioning_axes,
            conditioning_parents,
            texel_rest_normals,
            texel_skin_weights,
        )

        model.texel_pose.set_weights(texel_skin_weights(body.template, cond, R),
                                     conditioning_parents(body.template.joint_parents, cond),
                                     texel_rest_normals(body.template, R), conditioning_axes(body, cond, root))
        if model.shadows is not None:
            from uvatar.avh.shadows import texel_rest_points

            model.shadows.set_geometry(np.asarray(body.template.rest_joints, np.float32)[cond],
                                       conditioning_parents(body.template.joint_parents, cond),
                                       texel_rest_points(body.template, R))
    model = model.to(device)
    use_cuda = device.type == "cuda"
    if use_cuda:
        model = model.to(memory_format=torch.channels_last)
        torch.backends.cudnn.benchmark = True
    if ctx.active:  # before the optimizer takes the parameters: BatchNorm over the global batch
        model = global_batchnorm(model, device)
    opt = torch.optim.Adam(parameter_groups(model, cfg), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=cfg.lr_gamma)
    history: list[dict] = []
    start_epoch = 0
    if state is None:
        if model_config.pose_normalization:
            model.set_pose_statistics(train.pose_angles)
        tex_mean, disp_mean = mean_maps(train, excluded, cfg.outlier_threshold, cfg.displacement_weighting)
        if model.lights is not None and cfg.calibrate_lights:
            from uvatar.avh.lights import calibrate_rig

            m = train.maps
            with torch.no_grad():
                normals = model.texel_pose(train.pose_angles)[:, 6:9]
            tex_mean = calibrate_rig(model.lights, normals, m["texture"], texture_weight(m), steps=cfg.calibrate_lights)
        init_output_bias(model, tex_mean, disp_mean)
    else:
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        history, start_epoch = state["history"], state["epoch"] + 1
        torch.set_rng_state(state["rng"])
    ema = WeightAverage(model, cfg.ema_decay) if cfg.ema_decay > 0 else None
    if ema is not None and state is not None and state.get("ema") is not None:
        ema.load_state_dict(state["ema"])
    averaged = model if ema is None else ema.model  # what is validated, saved to model.pt and exported
    n_params = count_parameters(model)
    net = model
    if ctx.active:
        from torch.nn.parallel import DistributedDataParallel

        net = DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
    total = all_sum if ctx.active else None
    run_info = {"preset": preset_name, "model": model_config.to_dict(), "train": asdict(cfg), "baked": str(baked_dir.resolve()),
                "body_model": {"name": body_model_info(meta)[0],
                               "shapes": None if shapes is None else shapes.tolist()},
                "conditioning_joints": cond, "joint_names": joint_names,
                "train_frames": train.names, "val_frames": [] if val is None else val.names,
                "parameters": n_params, "displacement_frame": cfg.displacement_frame,
                "displacement_space": DISPLACEMENT_SPACES[cfg.displacement_frame]}
    if ctx.is_main:
        write_json(run_dir / "run.json", run_info)
        print(f"AVH generator: {n_params:,} parameters (f_c={model_config.feature_size}, "
              f"latent={model_config.latent}, {R}x{R}); {len(train)} train / "
              f"{0 if val is None else len(val)} val frames; device {device}"
              + (f"; {ctx.world} processes x {local_batch} samples" if ctx.active else ""))

    writer = None
    if cfg.tensorboard and ctx.is_main:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(run_dir / "tb"), purge_step=start_epoch)
    steps_per_epoch = math.ceil(len(train) / cfg.batch_size)
    bar = tqdm(total=(cfg.epochs - start_epoch) * steps_per_epoch, desc="train avh",
               disable=not (cfg.progress and ctx.is_main), unit="step")
    t0, samples = time.perf_counter(), 0
    for epoch in range(start_epoch, cfg.epochs):
        model.train()
        perm = torch.tensor(_epoch_order(len(train), epoch, cfg), dtype=torch.long).to(device)
        sums, step_losses = np.zeros(3), []
        for s in range(steps_per_epoch):
            idx = local_share(perm[s * cfg.batch_size:(s + 1) * cfg.batch_size], ctx)
            pose, batch = train.batch(idx, cfg.pose_noise)
            if use_cuda:
                batch = {k: v.contiguous(memory_format=torch.channels_last) for k, v in batch.items()}
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=use_cuda):
                tex, disp = net(*pose)
            losses = avh_loss(tex, disp, batch, excluded, cfg.outlier_threshold, cfg.displacement_weight, total,
                              cfg.displacement_weighting)
            opt.zero_grad(set_to_none=True)
            (losses[0] * ctx.world).backward()  # DDP averages over the world: undo it, the terms are shares
            opt.step()
            if ema is not None:
                ema.update(model)
            # this rank's shares summed over the ranks: the global batch's losses, and its size
            step = all_sum(torch.stack([x.detach().float() for x in losses] + [torch.tensor(
                float(len(idx)), device=device)])).cpu().double().numpy()
            sums += step[:3] * step[3]
            step_losses.append(float(step[0]))
            samples += int(step[3])
            bar.update(1)
            bar.set_postfix(epoch=epoch, loss=f"{step[0]:.2e}")
        sched.step()
        entry = {"epoch": epoch, "lr": opt.param_groups[0]["lr"],
                 **dict(zip(("loss", "texture", "displacement"), (sums / len(train)).tolist(), strict=True)),
                 "step_loss": step_losses}
        if not ctx.is_main:  # rank 0 alone validates, logs and writes the run folder
            history.append(entry)
            continue
        if val is not None:
            entry.update(dict(zip(("val_loss", "val_texture", "val_displacement"),
                                  evaluate_loss(averaged, val, excluded, cfg), strict=True)))
        history.append(entry)
        if writer is not None:
            for k, v in entry.items():
                if k not in ("epoch", "step_loss"):
                    writer.add_scalar(k.replace("val_", "val/") if k.startswith("val_") else f"train/{k}", v, epoch)
            if epoch % max(cfg.preview_every, 1) == 0 or epoch == cfg.epochs - 1:
                averaged.eval()
                writer.add_image("preview/pred_tex|gt_tex|pred_d|gt_d", _preview(averaged, val or train), epoch)
            writer.flush()
        model_state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
        averaged_state = {k: v.detach().cpu() for k, v in averaged.state_dict().items()}
        _save(ckpt_path, {"model": model_state, "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
                          "epoch": epoch, "history": history, "rng": torch.get_rng_state(),
                          "ema": None if ema is None else ema.state_dict(),
                          "model_config": model_config.to_dict(), "train_config": asdict(cfg)})
        _save(run_dir / "model.pt", {"model": averaged_state, "model_config": model_config.to_dict(), "epoch": epoch,
                                     "ema_decay": cfg.ema_decay})
        write_json(run_dir / "history.json", history)
    bar.close()
    if writer is not None:
        writer.close()
    ctx.barrier()  # the run folder is complete before any rank returns
    seconds = time.perf_counter() - t0
    if not history:
        raise UvatarError(f"{run_dir}: nothing trained (epochs={cfg.epochs})")
    summary = {"run": str(run_dir), "epochs": len(history), "parameters": n_params, "seconds": seconds,
               "samples_per_second": samples / seconds if seconds > 0 else None, "final": history[-1],
               "processes": ctx.world}
    gain_fit = cfg.fit_displacement_gain and val is not None
    recentre = cfg.recentre_displacement and model_config.output_bias
    if cfg.recentre_displacement and not model_config.output_bias:
        log.warning("recentre_displacement needs the generator's output bias (a CPU preset): not applied")
    if (gain_fit or recentre) and ctx.is_main:  # model.pt only: the checkpoint keeps the trained weights
        center = displacement_residual_mean(averaged, train, cfg.batch_size) if model_config.output_bias else None
        extra = {}
        if recentre:
            plain = mean_maps(train, excluded, cfg.outlier_threshold, "uniform")[1]
            recentre_displacement(averaged, center, plain)
            extra["displacement_recentred"] = True
        if gain_fit:
            gain, losses = fit_displacement_gain(averaged, val, excluded, cfg, center=center)
            scale_displacement_residual(averaged, gain, center)
            extra["displacement_gain"] = gain
            summary.update(displacement_gain=gain, displacement_gain_val_losses=losses)
        _save(run_dir / "model.pt", {"model": {k: v.detach().cpu() for k, v in averaged.state_dict().items()},
                                     "model_config": model_config.to_dict(), "epoch": len(history) - 1,
                                     "ema_decay": cfg.ema_decay, **extra})
    if ctx.is_main:
        write_json(run_dir / "done.json", summary)
    return summary


def load_trained_generator(run_dir: str | Path) -> tuple[AvhGenerator, dict]:
    """(generator in eval mode on CPU, run.json dict) from a training run folder; InputError for a run
    its stage record (:mod:`uvatar.stage_record`) marks unfinished."""
    run_dir = Path(run_dir)
    info_path, weights = run_dir / "run.json", run_dir / "model.pt"
    if not info_path.is_file() or not weights.is_file():
        raise InputError(run_dir, "not a training run (needs run.json and model.pt from `uvatar train avh`)")
    from uvatar.stage_record import require_complete

    # model.pt is written every epoch: a run killed (or failed) before its last is refused, not exported
    require_complete(run_dir, "train avh", f"uvatar train avh BAKED {run_dir} --resume", check_inputs=False)
    info = read_json(info_path)
    state = _load_checkpoint(weights)
    model = AvhGenerator(AvhConfig(**state["model_config"]))
    model.load_state_dict(state["model"])
    return model.eval(), info
