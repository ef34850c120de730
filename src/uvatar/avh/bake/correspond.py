"""Texel correspondences between the registered mesh M^R_t and the scan S_t (AVH §3.2.2).

For each valid texel with point r and unit normal n on M^R_t, one ray is cast along +n and one along
-n to the scan. A hit is a *positive* candidate when the scan normal m there is in the same
hemisphere as n (n . m > 0). Choice:

- one candidate: take it;
- both with the same polarity: the nearest;
- mixed polarity: the positive one, unless its distance is more than ``ratio`` (2) times the
  negative one's.

``choose_candidates`` is the vectorized rule; ``choose_candidates_reference`` its plain per-texel
twin (tests check parity).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uvatar.avh.bake.register import ScanSurface
from uvatar.devices import to_numpy

__all__ = ["TexelMatches", "choose_candidates", "choose_candidates_reference", "match_texels"]


@dataclass
class TexelMatches:
    """Matches for N query points (texels).

    hit: (N,) bool, a match was found; points: (N, 3) match x on the scan (zeros without a match);
    distance: (N,) metres from r to x (inf without a match); face: (N,) int64 scan face (-1);
    bary: (N, 3) barycentrics in that face; scan_normal: (N, 3) unit normal m of the scan at x;
    side: (N,) int8, +1 the +n ray, -1 the -n ray, 0 no match; positive: (N,) bool, n . m > 0;
    mixed: (N,) bool, both rays hit and their polarities differ (where the polarity rule acts);
    rule_changed: (N,) bool, the polarity rule chose the farther candidate (the choice differs from
    plain nearest); both None when not computed. on_device: the same fields as torch tensors where
    they were computed on a device (:func:`match_texels` of tensors), else None.
    """

    hit: np.ndarray
    points: np.ndarray
    distance: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    scan_normal: np.ndarray
    side: np.ndarray
    positive: np.ndarray
    mixed: np.ndarray | None = None
    rule_changed: np.ndarray | None = None
    on_device: dict | None = None


def choose_candidates(hit_plus, dist_plus, pos_plus, hit_minus, dist_minus, pos_minus,
                      polarity_rule: bool = True, ratio: float = 2.0) -> np.ndarray:
    """Pick between the +n and -n ray candidates. All inputs (N,); returns side (N,) int8 in {+1, -1, 0}.

    hit_*: bool, the ray hit the scan; dist_*: distance (metres); pos_*: bool, positive polarity.
    With ``polarity_rule=False`` (ablation) the nearest candidate always wins.
    """
    where, as_bool, int8 = _backend(hit_plus)
    hit_plus = as_bool(hit_plus)
    hit_minus = as_bool(hit_minus)
    dp = where(hit_plus, dist_plus, np.inf)
    dm = where(hit_minus, dist_minus, np.inf)
    nearest_plus = dp <= dm
    choose_plus = nearest_plus
    if polarity_rule:
        mixed = hit_plus & hit_minus & (as_bool(pos_plus) != as_bool(pos_minus))
        plus_is_positive = as_bool(pos_plus)
        # mixed: the positive wins unless it is more than ratio x farther than the negative
        positive_wins_plus = dp <= ratio * dm          # positive is the + candidate
        positive_wins_minus = dm <= ratio * dp         # positive is the - candidate
        mixed_plus = where(plus_is_positive, positive_wins_plus, ~positive_wins_minus)
        choose_plus = where(mixed, mixed_plus, nearest_plus)
    side = int8(where(choose_plus, 1, -1))
    side[~hit_plus & ~hit_minus] = 0
    side[hit_plus & ~hit_minus] = 1
    side[~hit_plus & hit_minus] = -1
    return side


def _backend(x):
    """(where, as bool, as int8) of numpy, or of torch for a tensor ``x``."""
    if type(x).__module__.startswith("torch"):
        import torch

        return torch.where, (lambda a: a.to(torch.bool)), (lambda a: a.to(torch.int8))
    return np.where, (lambda a: np.asarray(a, bool)), (lambda a: a.astype(np.int8))


def choose_candidates_reference(hit_plus, dist_plus, pos_plus, hit_minus, dist_minus, pos_minus,
                                polarity_rule: bool = True, ratio: float = 2.0) -> np.ndarray:
    """Plain per-texel twin of :func:`choose_candidates` (the paper's rule, written out)."""
    out = np.zeros(len(hit_plus), dtype=np.int8)
    for i in range(len(hit_plus)):
        cands = []
        if hit_plus[i]:
            cands.append((1, float(dist_plus[i]), bool(pos_plus[i])))
        if hit_minus[i]:
            cands.append((-1, float(dist_minus[i]), bool(pos_minus[i])))
        if not cands:
            continue
        if len(cands) == 1:
            out[i] = cands[0][0]
            continue
        a, b = cands  # a is the + ray
        if not polarity_rule or a[2] == b[2]:
            out[i] = a[0] if a[1] <= b[1] else b[0]
            continue
        positive, negative = (a, b) if a[2] else (b, a)
        out[i] = positive[0] if positive[1] <= ratio * negative[1] else negative[0]
    return out


def match_texels(points, normals, scan: ScanSurface, polarity_rule: bool = True, ratio: float = 2.0,
                 max_distance: float | None = None, epsilon: float = 1e-4) -> TexelMatches:
    """Cast the two texel rays and choose per texel. points r (N, 3), unit normals n (N, 3) on M^R_t.

    Rays start ``epsilon`` metres behind r (so a scan surface through r is found by both) and reach
    ``max_distance`` metres (None: unlimited). Batched through Embree (two calls for all texels).
    points and normals as float64 torch tensors: the rays are cast (:meth:`RayCaster.first_hit_torch`)
    and the choice made on their device, the same steps; the matches come back as numpy arrays.
    """
    on_torch = type(points).__module__.startswith("torch")
    if on_torch:
        import torch

        r, n = points, normals
        where = torch.where
        limit = None if max_distance is None else torch.full((len(r),), float(max_distance) + epsilon,
                                                              dtype=torch.float64, device=r.device)

        def cast(o, d):
            return scan.caster.first_hit_torch(o, d, limit)

        def floor(x):
            return x.clamp_min(0.0)
    else:
        r = np.asarray(points, dtype=np.float64)
        n = np.asarray(normals, dtype=np.float64)
        where = np.where
        limit = np.inf if max_distance is None else float(max_distance) + epsilon

        def cast(o, d):
            return scan.caster.first_hit(o, d, max_distance=limit)

        def floor(x):
            return np.maximum(x, 0.0)
    cand = []
    for sign in (1.0, -1.0):
        d = sign * n
        hits = cast(r - epsilon * d, d)
        m = scan.normals_at_hits(hits)
        dist = floor(hits.distance - epsilon)
        cand.append((hits, m, dist, (m * n).sum(1) > 0))
    (hp, mp, dp, pp), (hm, mm, dm, pm) = cand
    side = choose_candidates(hp.hit, dp, pp, hm.hit, dm, pm, polarity_rule, ratio)
    nearest = choose_candidates(hp.hit, dp, pp, hm.hit, dm, pm, False, ratio)
    mixed = hp.hit & hm.hit & (pp != pm)
    plus = side == 1
    pick = lambda a, b: where(plus.reshape(-1, *([1] * (a.ndim - 1))), a, b)  # noqa: E731
    hit = side != 0
    distance = where(hit, pick(dp, dm), np.inf)
    face = where(hit, pick(hp.face, hm.face), -1)
    mask3 = hit[:, None]
    matches = TexelMatches(
        hit=hit,
        points=where(mask3, pick(hp.points, hm.points), 0.0),
        distance=distance,
        face=face,
        bary=where(mask3, pick(hp.bary, hm.bary), 0.0),
        scan_normal=where(mask3, pick(mp, mm), 0.0),
        side=side,
        positive=hit & pick(pp, pm),
        mixed=mixed,
        rule_changed=side != nearest,
    )
    if on_torch:
        kept = {name: value for name, value in vars(matches).items() if value is not None}
        for name, value in kept.items():
            setattr(matches, name, to_numpy(value))
        matches.on_device = kept
    return matches
