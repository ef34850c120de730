"""The ``--eval`` ablation: re-bake a few frames without each step of the paper and score them.

Variants: ``full``; ``no_registration`` (neither the articulated pose refinement nor the vertex
stages); ``no_pose_refinement``; ``no_vertex_registration``; ``no_polarity_rule`` (nearest candidate
always); ``no_registration_no_polarity_rule`` (the rule's effect when the texel rays start on the
unregistered shadow mesh, centimetres from the scan); ``no_colour_refinement`` (each frame refined
alone against its scan, without the cross-frame colour term; listed when the bake used it). Per variant, over the full pipeline's confident texels (kappa > threshold) that the variant
also matched: median / p90 error and texture PSNR; over its own confident texels: median error and
the confident fraction of valid texels.

Because a step that changes few texels cannot move an overall median, each variant also reports
``changed``: the texels (among its base's confident ones matched by both; the base is the full
pipeline, or ``no_registration`` for ``no_registration_no_polarity_rule``) where its correspondence
differs from the base's by more than ``change_tolerance_m``, with the median error of both there;
``changed.all_matched`` the same over every texel both matched, confident or not. For the polarity rule this is exactly the set of texels with mixed-polarity
candidates where the rule picks the farther (positive) candidate; ``mixed_polarity_texels`` counts
all texels with mixed candidates.

``texture_ceiling_psnr_db``: the exact gt texture sampled through the scan's own atlas at the true
surface points (rays along the true normal, +-2 cm) against the exact gt, on the full pipeline's
confident texels: what a perfect correspondence could score with this scan texture (its atlas
resolution and bilinear blur). Needs the exact gt reference.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from uvatar.avh.bake.metrics import error_summary, pooled_psnr, texel_errors

__all__ = ["ablation_variants", "run_ablation", "variant_input"]

CHANGE_TOLERANCE_M = 1e-4


def ablation_variants(bake_cfg) -> dict:
    variants = {"full": bake_cfg, "no_registration": replace(bake_cfg, register=False, refine_pose=False),
                "no_pose_refinement": replace(bake_cfg, refine_pose=False),
                "no_vertex_registration": replace(bake_cfg, register=False),
                "no_polarity_rule": replace(bake_cfg, polarity_rule=False),
                "no_registration_no_polarity_rule": replace(bake_cfg, register=False, refine_pose=False,
                                                            polarity_rule=False)}
    if bake_cfg.refines_across_frames:
        variants["no_colour_refinement"] = replace(bake_cfg, pose_refine=replace(bake_cfg.pose_refine,
                                                                                 photometric_weight=0.0))
    return variants


def variant_input(cfg, stored_fit, capture_fit):
    """(fit, config) a variant bakes one frame from. The colour refinement needs every frame, so a
    variant that keeps it takes the bake's stored fit (already refined, baked as is); the others start
    from the capture's fit (refined alone against the scan when the variant refines)."""
    if cfg.refines_across_frames and stored_fit is not None:
        return stored_fit, replace(cfg, refine_pose=False)
    return capture_fit, cfg


# the variant each one's ``changed`` texels are measured against (default: the full pipeline)
CHANGE_BASE = {"no_registration_no_polarity_rule": "no_registration"}


def _new_tally() -> dict:
    return {"count": 0, "of": 0, "with": [], "without": []}


def _tally(acc: dict, base, variant, scored, moved, gt) -> None:
    """Add one frame to ``acc``: of the ``scored`` texels, those whose match ``moved`` between the
    base bake and the variant, with the errors of both there."""
    diff = scored & moved
    acc["count"] += int(diff.sum())
    acc["of"] += int(scored.sum())
    acc["with"].append(texel_errors(base.points, base.texture, diff, *gt)[0])
    acc["without"].append(texel_errors(variant.points, variant.texture, diff, *gt)[0])


def _ceiling_sq(scan, gt_surface, gt_normal, gt_texture, sel):
    """Squared errors (K, 3) of the gt texture sampled through the scan atlas at the true points."""
    from uvatar.avh.bake.correspond import match_texels
    from uvatar.avh.bake.register import ScanSurface
    from uvatar.geometry import sample_mesh_texture

    surface = ScanSurface.build(scan.vertices, scan.faces)
    m = match_texels(gt_surface[sel], gt_normal[sel], surface, True, 2.0, 0.02, 1e-4)
    colours = sample_mesh_texture(scan.uvs, scan.uv_faces, scan.texture, m.face[m.hit], m.bary[m.hit])
    return (np.asarray(colours, np.float64) - gt_texture[sel][m.hit]) ** 2


def run_ablation(capture, body, layout, bake_cfg, confident: dict, config, source, progress: bool,
                 stored_fits: dict | None = None) -> dict:
    """Re-bake the chosen frames per variant; ``confident`` {frame: (R, R) bool} of the full bake;
    ``source`` a GtSource; ``stored_fits`` {frame: BodyFit} the fits the bake stored (see
    :func:`variant_input`)."""
    from tqdm import tqdm

    from uvatar.avh.bake.frame import bake_fit

    names = sorted(confident)
    if config.ablation_frames is not None and len(names) > config.ablation_frames:
        names = [names[i] for i in np.linspace(0, len(names) - 1, config.ablation_frames).round().astype(int)]
    variants = ablation_variants(bake_cfg)
    keys = list(variants)
    common = {k: [] for k in keys}
    common_sq = {k: [] for k in keys}
    own = {k: [] for k in keys}
    coverage = {k: [] for k in keys}
    # per variant, over its base's confident texels and over every texel both matched
    changed = {k: {scope: _new_tally() for scope in ("confident", "all")} for k in keys if k != "full"}
    mixed, ceiling_sq = 0, []
    own_conf = {}
    for f in tqdm(names, desc="ablation", unit="frame", disable=not progress):
        gt = source.get(f)
        fit = capture.load_fit(f)
        shape = None if fit.shapes.size else (capture.body_shapes if capture.body_shapes.size else None)
        scan = capture.load_scan(f)
        baked = {}
        for name, cfg in variants.items():
            variant_fit, variant_cfg = variant_input(cfg, (stored_fits or {}).get(f), fit)
            b, _ = bake_fit(body, variant_fit, layout, scan, variant_cfg, shape)
            baked[name] = b
            score_common = confident[f] & b.matched
            e, q = texel_errors(b.points, b.texture, score_common, *gt)
            common[name].append(e)
            common_sq[name].append(q)
            score_own = b.valid & (b.kappa > config.kappa_threshold)
            own[name].append(texel_errors(b.points, b.texture, score_own, *gt)[0])
            coverage[name].append(score_own.sum() / max(b.valid.sum(), 1))
            own_conf[name] = confident[f] if name == "full" else score_own
        full = baked["full"]
        mixed += int(full.stats.get("mixed_polarity_texels", 0))
        for name, ch in changed.items():
            base_name = CHANGE_BASE.get(name, "full")
            base, variant = baked[base_name], baked[name]
            matched = base.matched & variant.matched & gt[2]
            moved = np.linalg.norm(base.points - variant.points, axis=-1) > CHANGE_TOLERANCE_M
            _tally(ch["confident"], base, variant, own_conf[base_name] & matched, moved, gt)
            # the same over every texel both matched, confident or not (where a rare step acts)
            _tally(ch["all"], base, variant, base.valid & matched, moved, gt)
        if source.renderer is not None:
            g = source.renderer.render(f)
            ceiling_sq.append(_ceiling_sq(scan, g["surface"], g["normal"], g["texture"].astype(np.float64),
                                          confident[f] & g["mask"]))
    out = {"frames": names, "change_tolerance_mm": CHANGE_TOLERANCE_M * 1000,
           "mixed_polarity_texels": mixed,
           "texture_ceiling_psnr_db": pooled_psnr(ceiling_sq) if ceiling_sq else None}
    for name in keys:
        common_summary = error_summary(common[name])
        out[name] = {"median_mm": common_summary["median"],
                     "p90_mm": common_summary["p90"],
                     "texture_psnr_db": pooled_psnr(common_sq[name]),
                     "median_mm_own_confident_texels": error_summary(own[name])["median"],
                     "confident_fraction": float(np.mean(coverage[name]))}
        if name in changed:
            conf, every = changed[name]["confident"], changed[name]["all"]
            with_, without = error_summary(conf["with"]), error_summary(conf["without"])
            out[name]["changed"] = {"against": CHANGE_BASE.get(name, "full"), "texels": conf["count"],
                                    "fraction": conf["count"] / max(conf["of"], 1),
                                    "median_mm_with": with_["median"], "median_mm_without": without["median"],
                                    "p90_mm_with": with_["p90"], "p90_mm_without": without["p90"],
                                    "all_matched": {"texels": every["count"],
                                                    "fraction": every["count"] / max(every["of"], 1),
                                                    "median_mm_with": error_summary(every["with"])["median"],
                                                    "median_mm_without": error_summary(every["without"])["median"]}}
    return out
