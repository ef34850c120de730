"""``uvatar demo``: synth → (fit) → bake (+ eval against ground truth) → select → train → export → animate an
unseen motion → eval on held-out poses → ``OUT/metrics.json`` and ``OUT/report.html``.

Each stage calls the library function behind its command (:func:`~uvatar.capture.synth.pipeline.synthesize`,
:func:`~uvatar.avh.bake.pipeline.bake_capture`, ...) in process. The demo's own progress is a stage record
(:mod:`uvatar.stage_record`), ``OUT/stage.json``: the settings that shape its outputs (every
:class:`DemoConfig` field but ``workers`` and ``progress``), how many stages are finished and the seconds
each took. A stage counts as finished once every output of it is written, so a demo killed at any point
resumes after the last finished stage: the stage cut short runs again (and itself resumes what it
finished: frames, epochs), later stages run after it. A rerun with other settings is refused in one line
naming the first difference (the outputs on disk were made with the old ones). With ``fits="fit"`` the
studio's own fits are moved out of the capture (to ``OUT/studio_fits/``) and ``uvatar fit --from scans``
makes the fits the rest of the pipeline uses, as for a real capture.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from uvatar import stage_record
from uvatar.errors import InputError, UvatarError
from uvatar.io_utils import write_json

log = logging.getLogger(__name__)

FIT_SOURCES = ("studio", "fit")
# the DemoConfig fields `uvatar demo` has a flag for (cli/demo.py); the others come from its size preset
FLAG_FIELDS = ("seed", "epochs", "fits", "orientation", "progress")
# fields that do not shape the demo's outputs (left out of its stage record)
_VOLATILE = ("workers", "progress")


@dataclass(frozen=True)
class DemoConfig:
    """Sizes of the demo run. ``DEFAULT``: 128² maps, both conditionings (8.1 min on an idle 2-core CPU).
    ``FINE`` (``uvatar demo --fine``): 256² maps (``texels=256, preset="cpu-256"``), 12.0 min there, over
    the 10 minutes a first run should take, so not the default (docs/results.md). ``QUICK`` ~3 min alone."""

    frames: int = 100           # synthetic capture frames in all (takes + held-out poses)
    heldout: int = 8            # held-out frames with poses not in the takes
    cameras: int = 4
    image_size: int = 256
    scan_texture: int = 512
    gt_texels: int = 256
    texels: int = 128           # bake resolution = the generator preset's output resolution
    train_frames: int = 80
    val_frames: int = 6
    preset: str = "cpu-small"
    # generator conditionings trained (AvhConfig.conditioning); the first is the demo's avatar (OUT/run,
    # OUT/avatar), each other one gets OUT/run_<c>, OUT/avatar_<c> and is evaluated beside it
    conditionings: tuple[str, ...] = ("texel", "global")
    # what the generators' pose input holds (AvhConfig.orientation): "studio" adds the body's orientation in
    # the capture's world, since the synthetic studio's light rig is fixed in it (SynthConfig.light)
    orientation: str = "studio"
    # the texel + studio generator's light-rig shading head and its cast shadows / occlusion from the posed
    # limbs (AvhConfig.shading_lights / shading_shadows / shading_occlusion; docs/results.md, issue #24)
    shading_lights: int = 2
    shading_shadows: bool = True
    shading_occlusion: bool = True
    # the exported weights are their moving average (TrainConfig.ema_decay): lower validation loss
    ema_decay: float = 0.99
    # after training, the displacement's mean over the training frames is reset to the plain mean of their
    # kept texels, the eval's R² reference, instead of the w-weighted mean training converges to
    # (TrainConfig.recentre_displacement; held-out displacement R² -0.128 -> -0.101, texture the same;
    # docs/results.md, issue #38 item 6). `uvatar train avh` (the paper's training) keeps it off
    recentre_displacement: bool = True
    epochs: int = 40
    animate_frames: int = 48
    animate_size: int = 256
    seed: int = 0
    workers: int = 2
    synth_preset: str = "default"  # "quick": small scans (6k-12k faces), short topology segments
    fits: str = "studio"        # "studio": the studio's noisy fits; "fit": made by `uvatar fit --from scans`
    progress: bool = True       # progress bars of the stages

    def __post_init__(self) -> None:
        from uvatar.avh.model import CONDITIONINGS, ORIENTATIONS
        from uvatar.errors import check_values

        check_values([(self.fits in FIT_SOURCES, f"fits must be one of {', '.join(FIT_SOURCES)}, got {self.fits!r}"),
                      (self.orientation in ORIENTATIONS,
                       f"orientation must be one of {', '.join(ORIENTATIONS)}, got {self.orientation!r}"),
                      (self.epochs >= 1, f"epochs must be at least 1, got {self.epochs}"),
                      (self.shading_lights >= 0, f"shading_lights must be >= 0, got {self.shading_lights}"),
                      (not self.shading_shadows or self.shading_lights >= 1, "shading_shadows needs shading_lights >= 1"),
                      (not self.shading_occlusion or self.shading_shadows, "shading_occlusion needs shading_shadows"),
                      (0 <= self.ema_decay < 1, f"ema_decay must be in [0, 1), got {self.ema_decay}"),
                      (len(self.conditionings) >= 1 and len(set(self.conditionings)) == len(self.conditionings)
                       and set(self.conditionings) <= set(CONDITIONINGS),
                       f"conditionings must be distinct values of {', '.join(CONDITIONINGS)}, "
                       f"got {', '.join(self.conditionings)}")])


DEFAULT = DemoConfig()
# 256² maps: the plaid and the creases survive (docs/results.md, issue #24)
FINE = DemoConfig(texels=256, preset="cpu-256")
QUICK = DemoConfig(frames=12, heldout=3, cameras=2, image_size=96, scan_texture=256, gt_texels=64,
                   texels=64, train_frames=8, val_frames=2, preset="cpu-tiny", epochs=2,
                   animate_frames=6, animate_size=96, synth_preset="quick")


@dataclass
class StageResult:
    name: str
    status: str                 # "ran", "skipped (done)", "failed: ...", "not run (...)"
    seconds: float = 0.0
    outputs: dict = field(default_factory=dict)


SIZES = {"default": DEFAULT, "quick": QUICK, "fine": FINE}
# how a message names each size preset (`uvatar demo` spells quick=True as --quick)
_SIZE_WORDS = {"default": "the default sizes", "quick": "quick=True", "fine": "fine=True"}


def demo_record_config(cfg: DemoConfig) -> dict:
    """The settings of ``OUT/stage.json``: every :class:`DemoConfig` field that shapes the outputs."""
    return stage_record.config_values(cfg, drop=_VOLATILE)


def _sizes_of(values: dict) -> str | None:
    """The size preset (``SIZES``) whose fields no flag sets ``values`` has, or None (a config of its own)."""
    for name, preset in SIZES.items():
        if all(values.get(k) == v for k, v in demo_record_config(preset).items() if k not in FLAG_FIELDS):
            return name
    return None


def _refuse_other_sizes(out: Path, values: dict, redo_hint: str) -> None:
    """A demo made with another size preset than this run's is refused naming the presets (--quick,
    --fine), not the first of the many fields they set (no flag sets those); any other difference is
    left to :func:`uvatar.stage_record.begin`, which names the setting."""
    previous = stage_record.read_record(out)
    if previous is None or previous.get("stage") != "demo":
        return
    before = previous["config"]
    first = stage_record.first_config_difference(before, values)
    if first is None or first in FLAG_FIELDS:
        return
    old, new = _sizes_of(before), _sizes_of(values)
    if old is not None and new is not None and old != new:
        raise InputError(out, f"made with {_SIZE_WORDS[old]} (this run: {_SIZE_WORDS[new]}); rerun with the same "
                              f"settings to resume it, or {redo_hint}")


def run_dirs(out: Path, cfg: DemoConfig) -> dict[str, tuple[Path, Path]]:
    """{conditioning: (run folder, avatar folder)}; the first conditioning owns OUT/run and OUT/avatar."""
    out = Path(out)
    return {c: (out / "run", out / "avatar") if i == 0 else (out / f"run_{c}", out / f"avatar_{c}")
            for i, c in enumerate(cfg.conditionings)}


def demo_stages(out: Path, cfg: DemoConfig) -> list[tuple[str, Callable[[], None]]]:
    """The pipeline as (stage name, function that runs it and writes its outputs)."""
    out = Path(out)
    cap, baked, avatar = out / "capture", out / "baked", out / "avatar"

    def synth() -> None:
        from uvatar.capture.synth.config import preset
        from uvatar.capture.synth.pipeline import synthesize

        summary = synthesize(cap, preset(cfg.synth_preset, frames=cfg.frames, heldout=cfg.heldout,
                                         cameras=cfg.cameras, image_size=cfg.image_size,
                                         scan_texture=cfg.scan_texture, gt_texels=cfg.gt_texels, seed=cfg.seed,
                                         workers=cfg.workers), progress=cfg.progress)
        if summary["failed"]:
            raise UvatarError(f"{cap}: synth failed on frame(s) {', '.join(sorted(summary['failed']))[:200]}")

    def fit() -> None:
        import shutil

        from uvatar.body.registry import load_body_model
        from uvatar.capture import Capture
        from uvatar.fit.evaluate import evaluate_fits
        from uvatar.fit.pipeline import FitConfig, fit_capture

        studio = out / "studio_fits"
        if (cap / "fits").is_dir() and not studio.exists():  # the studio's fits leave the capture once
            shutil.move(str(cap / "fits"), str(studio))
        summary = fit_capture(cap, FitConfig(source="scans", force=True), progress=cfg.progress)
        capture = Capture(cap)
        body = load_body_model(capture.body_model)
        fits = {f: capture.load_fit(f) for f in capture.frames}
        metrics = {"fit": evaluate_fits(body, capture, fits, capture.body_shapes),
                   "seconds": summary["seconds"], "contact_sheet": summary.get("contact_sheet")}
        if studio.is_dir():
            from uvatar.capture.fits import read_fits_dir

            metrics["studio_fits"] = evaluate_fits(body, capture, read_fits_dir(studio), None)
        write_json(out / "fit_metrics.json", metrics)

    def bake() -> None:
        from uvatar.avh.bake import BakeConfig
        from uvatar.avh.bake.dataset import read_dataset_info
        from uvatar.avh.bake.evaluate import EvalConfig, evaluate_bake
        from uvatar.avh.bake.pipeline import bake_capture

        bake_capture(cap, baked, BakeConfig().with_updates(texels=cfg.texels), None, cfg.workers, cfg.progress)
        info = read_dataset_info(baked)
        if not info.get("frames_baked"):
            raise UvatarError(f"{baked}: no frame was baked (rejected: {len(info.get('rejected', {}))})")
        metrics = evaluate_bake(cap, baked, EvalConfig(), cfg.progress)
        write_json(out / "bake_metrics.json", {"frames_baked": len(info["frames_baked"]),
                                               "rejected": info.get("rejected", {}), "eval": metrics})

    def select() -> None:
        from uvatar.avh.bake.select import SelectConfig, select_from_baked

        select_from_baked(baked, SelectConfig(n_train=cfg.train_frames, n_val=cfg.val_frames, seed=cfg.seed))

    def train() -> None:
        from uvatar.avh.model import preset
        from uvatar.avh.train import TrainConfig, train_avh

        for conditioning, (run_dir, _) in run_dirs(out, cfg).items():
            # the light rig belongs to the shading head, which only texel + studio has (the global
            # generator trains without it, as it always did: AvhConfig refuses lights it would ignore)
            lit = conditioning == "texel" and cfg.orientation == "studio"
            model = preset(cfg.preset, conditioning=conditioning, orientation=cfg.orientation,
                           shading_lights=cfg.shading_lights if lit else 0,
                           shading_shadows=cfg.shading_shadows and lit, shading_occlusion=cfg.shading_occlusion and lit)
            train_avh(baked, run_dir, model, TrainConfig(epochs=cfg.epochs, ema_decay=cfg.ema_decay,
                                                         recentre_displacement=cfg.recentre_displacement,
                                                         progress=cfg.progress), resume=True, preset_name=cfg.preset)

    def export() -> None:
        from uvatar.avh.export import export_avatar

        for run_dir, avatar_dir in run_dirs(out, cfg).values():
            export_avatar(run_dir, avatar_dir)

    def animate() -> None:
        from uvatar.avh.animate import AnimateConfig
        from uvatar.avh.animate import animate as render_motion

        render_motion(avatar, f"heldout:{cap}", out / "animation.mp4",
                      AnimateConfig(size=cfg.animate_size, max_frames=cfg.animate_frames, progress=cfg.progress))

    def evaluate() -> None:
        from uvatar.avh.eval import EvalConfig, evaluate_avatar

        dirs = run_dirs(out, cfg)
        others = {f"avh_{c}": avatar_dir for c, (_, avatar_dir) in list(dirs.items())[1:]}
        write_json(out / "eval.json", evaluate_avatar(avatar, cap, EvalConfig(progress=cfg.progress),
                                                      image_dir=out / "eval_images",
                                                      others=others))

    fit_stage = [("fit", fit)] if cfg.fits == "fit" else []
    return [("synth", synth), *fit_stage, ("bake", bake), ("select", select), ("train", train), ("export", export),
            ("animate", animate), ("eval", evaluate)]


def run_demo(out: str | Path = "demo_out", cfg: DemoConfig = DEFAULT,
             on_stage: Callable[[str], None] | None = None) -> dict:
    """Run the stages after the last finished one (``OUT/stage.json``); return (and write) ``OUT/metrics.json``.

    A rerun with other settings than the demo in ``out`` was made with is refused in one line
    (:class:`~uvatar.errors.InputError`) before any work. A stage that raises
    :class:`~uvatar.errors.UvatarError` is reported as failed and the later stages are not run (a rerun
    starts at it); an ``OSError`` (the file system said no) propagates.
    """
    from uvatar.demo.report import write_demo_report

    out = Path(out)
    stages = demo_stages(out, cfg)
    values, redo_hint = demo_record_config(cfg), "use out=OTHER to start over"
    _refuse_other_sizes(out, values, redo_hint)
    state = stage_record.begin(out, "demo", values, total=len(stages), skip_complete=True, redo_hint=redo_hint)
    finished = state.done if state.status in ("resume", "complete") else 0
    results: list[StageResult] = []
    failed = False
    for index, (name, stage) in enumerate(stages):
        if on_stage:
            on_stage(name)
        if failed:
            results.append(StageResult(name, "not run (an earlier stage failed)"))
            continue
        if index < finished:
            results.append(StageResult(name, "skipped (done)"))
            continue
        log.info("demo: stage %s", name)
        t0 = time.perf_counter()
        try:
            stage()
        except UvatarError as exc:
            failed = True
            log.error("demo: stage %s failed: %s", name, exc)
            results.append(StageResult(name, f"failed: {str(exc).splitlines()[0][:300]}", time.perf_counter() - t0))
            continue
        dt = time.perf_counter() - t0
        # after every output of the stage: it is finished
        stage_record.mark_progress(out, index + 1, details={"seconds": {**_recorded_seconds(out), name: dt}})
        results.append(StageResult(name, "ran", dt))
    if not failed:
        stage_record.finish(out)
    metrics = collect_metrics(out, cfg, results)
    write_json(out / "metrics.json", metrics)
    write_demo_report(out, metrics)
    return metrics


def _recorded_seconds(out: Path) -> dict:
    """{stage: seconds it took} of the finished stages, from ``OUT/stage.json``."""
    record = stage_record.read_record(out) or {}
    seconds = (record.get("details") or {}).get("seconds")
    return dict(seconds) if isinstance(seconds, dict) else {}


def _load(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def collect_metrics(out: Path, cfg: DemoConfig, results: list[StageResult]) -> dict:
    """Merge the stage JSONs into one metrics object (``avh``, ``baselines``, ``bake``, ``stages``)."""
    evaluation = _load(out / "eval.json") or {}
    metrics: dict = {
        "config": asdict(cfg),
        "stages": [asdict(r) for r in results],
        # the seconds each finished stage took when it ran (in this run or an earlier one)
        "stage_seconds": _recorded_seconds(out),
        "bake": _load(out / "bake_metrics.json"),
    }
    fit = _load(out / "fit_metrics.json")
    if fit:
        keep = ("mpjpe_mm", "mpjpe_median_mm", "angle_error_deg", "scan_to_body_median_mm", "shape_error_mm", "frames")
        metrics["fit"] = {name: {k: fit[name].get(k) for k in keep} for name in ("fit", "studio_fits") if fit.get(name)}
        metrics["fit"]["seconds"] = fit.get("seconds")
    if evaluation:
        metrics["avh"] = evaluation.get("avh")
        metrics["avh_conditioning"] = cfg.conditionings[0]
        metrics["avh_orientation"] = cfg.orientation
        # every trained conditioning under its name (the first is metrics["avh"], the others eval's "others")
        metrics["avh_by_conditioning"] = {c: evaluation.get("avh") if i == 0 else (evaluation.get("others") or {}).get(
            f"avh_{c}") for i, c in enumerate(cfg.conditionings)}
        metrics["baselines"] = evaluation.get("baselines")
        metrics["protocol"] = evaluation.get("protocol")
        for key in ("nearest_training_distance_deg", "distance_bins", "avatars", "bake_ceiling"):
            metrics[key] = evaluation.get(key)
    export = _load(out / "avatar" / "avatar.json")
    if export:
        metrics["export"] = {k: export[k] for k in ("onnx_max_abs_diff", "parameters", "preset") if k in export}
    return metrics


def quick_config(**overrides) -> DemoConfig:
    return replace(QUICK, **overrides)
