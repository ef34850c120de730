"""The polarity rule on an analytic scan: the true surface (facing +z) above the texel and an inner
sheet facing -z below it; match_texels reports mixed candidates and where the rule changed the pick."""

from __future__ import annotations

import numpy as np

from uvatar.avh.bake.correspond import match_texels
from uvatar.avh.bake.register import ScanSurface


def _plane(z, up: bool, size=0.2):
    v = np.array([[-size, -size, z], [size, -size, z], [size, size, z], [-size, size, z]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]]) if up else np.array([[0, 2, 1], [0, 3, 2]])
    return v, f


def _scan(outer_mm, inner_mm):
    v1, f1 = _plane(outer_mm / 1000, up=True)      # the true surface: positive for n = +z
    v2, f2 = _plane(-inner_mm / 1000, up=False)    # an inner sheet facing -z: negative
    return ScanSurface.build(np.concatenate([v1, v2]), np.concatenate([f1, f2 + 4]))


def _match(scan, rule):
    r = np.zeros((1, 3))
    n = np.array([[0.0, 0.0, 1.0]])
    return match_texels(r, n, scan, polarity_rule=rule, ratio=2.0, max_distance=0.05, epsilon=1e-6)


def test_rule_prefers_the_positive_candidate_within_twice_the_distance():
    scan = _scan(outer_mm=3.0, inner_mm=2.0)        # the negative sheet is nearer
    with_rule, nearest = _match(scan, True), _match(scan, False)
    assert with_rule.mixed[0] and nearest.mixed[0]
    assert with_rule.side[0] == 1 and with_rule.positive[0]
    np.testing.assert_allclose(with_rule.distance[0], 0.003, atol=1e-5)
    assert nearest.side[0] == -1 and not nearest.positive[0]
    np.testing.assert_allclose(nearest.distance[0], 0.002, atol=1e-5)
    assert with_rule.rule_changed[0] and not nearest.rule_changed[0]


def test_rule_keeps_the_negative_candidate_beyond_twice_the_distance():
    m = _match(_scan(outer_mm=5.0, inner_mm=2.0), True)
    assert m.mixed[0] and m.side[0] == -1 and not m.rule_changed[0]


def test_same_polarity_is_not_mixed():
    v1, f1 = _plane(0.003, up=True)
    v2, f2 = _plane(-0.002, up=True)                # both face +z: same polarity, nearest wins
    scan = ScanSurface.build(np.concatenate([v1, v2]), np.concatenate([f1, f2 + 4]))
    m = _match(scan, True)
    assert not m.mixed[0] and not m.rule_changed[0] and m.side[0] == -1
