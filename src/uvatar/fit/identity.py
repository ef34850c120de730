"""The subject as one track through the take: never a silent switch to another person (issue 41).

Per frame, :func:`uvatar.fit.observe.observe_frame` detects the subject in a crop around the
previous frame's keypoints; with another person close, that crop holds both, and the detector may
take the other one in most views (on a real two-person take the fit jumped 1.25 m to the other
person in one frame and stayed there). :class:`SubjectTracker` judges every frame's observation:

- **Motion**: the subject is an :class:`Identity` with a position (the centre of the triangulated
  torso, :func:`body_centre`) and a velocity; the next position is predicted, and an observation
  counts as the subject only inside the gate a person can reach: ``max_speed`` (m/s) times the time
  since the subject was last seen, plus :data:`SLACK_M` (triangulation noise).
- **Everyone near**: the other people are found (:func:`uvatar.fit.person.find_people`, every
  :data:`SURVEY_EVERY` frames, and every frame while someone is within :data:`NEAR_M` of the
  subject or the observation is doubtful) and tracked as identities of their own, with the same gate
  (a new one only where it is seen beside the subject: while the subject is held, a newcomer may be
  the subject itself). A person better explained by another identity's track is not the subject.
- **Build**: a crop that holds two people can give a skeleton made of both (the detector took one
  person in some views and the other in the rest); its bones are stretched between them, so an
  observation whose bone lengths lie more than :data:`MIX_BUILD` from the subject's build so far
  (:func:`~uvatar.fit.person.same_body`) is not the subject.
- **Appearance**: every identity has a colour model: an RGB histogram (:data:`HIST_BINS`^3 bins) of
  the pixels inside its torso (shoulders and hips) in every view where nobody else overlaps it
  (:func:`torso_histograms`, :meth:`Candidate.clean_hists`). Where the positions do not decide, the colours may.
- **Close, held**: a skeleton found while another person is within :data:`CLOSE_M` of the subject
  may be a mix of both (on the synthetic crossing, mixes lay 0.1-0.3 m from each person: inside
  the gates, with bones of a plausible length), and a track fed with one drifts onto the other
  person. So from the first frame where someone is that close (another candidate of the frame, or
  another track seen in the last :data:`NEAR_FRAMES` frames), the frame is ``crowded``: held, and
  every track stands still, until the subject is seen apart from everyone (the one nearest its last
  place, others farther than ``CLOSE_M``) in :data:`APART_FRAMES` frames in a row, or alone for
  :data:`CLOSE_EXPIRE` frames. Beyond ``CLOSE_M``, the keypoints inside another person's box in a
  view are still left out (:func:`~uvatar.fit.identity_frame.clear_of_others`); too few left is ``crowded`` too.
- **Held, never guessed**: where no person is the subject (hidden, out of view) the frame is
  ``lost``; where two people could be the subject and neither position nor colours tell them apart,
  ``ambiguous``. Held frames (``lost``, ``ambiguous``, ``crowded``) are left out of the fit (no
  keypoints, no fit written); after a hold the subject is taken back (``reassociated``,
  :meth:`SubjectTracker._reassociate`) only as the person nearest its last place, decisively
  nearer than anyone else and nearer than any other person's last place, of its build, with
  colours that are not clearly another's; the other people's tracks start again from the people
  apart from it.
- **Jumps**: a cut to another take (the synthetic studio's takes) moves the subject beyond its
  gate; it is taken back (``reassociated``) where one person is there whom no other track is near
  (:data:`JUMP_CLEAR` gates), of the subject's build, with colours clearly the subject's rather
  than every other person's; with nobody else ever seen, the one person in view.

A cut detected by the caller (every keypoint jumps and the images change, :mod:`uvatar.fit.tracking`)
with nobody else ever seen restarts the track (the person of the subject's build found again).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["SLACK_M", "NEAR_M", "SURVEY_EVERY", "HIST_BINS", "body_centre", "torso_histograms", "hist_distance",
           "Identity", "Candidate", "SubjectTracker", "STATUSES"]

STATUSES = ("lost", "ambiguous", "crowded")   # the held statuses (no fit), as reported

SLACK_M = 0.15        # metres added to the motion gate (triangulation noise, a torso bending)
NEAR_M = 1.0          # another person within this of the subject: everyone is found every frame
SURVEY_EVERY = 2      # frames between looks for other people when nobody is near
FORGET_FRAMES = 50    # another person unseen this long is forgotten
NEAR_FRAMES = 10      # another person seen this recently still keeps the subject's views it overlaps
DECISIVE = 0.5        # a gate-relative distance this share of the next one decides alone
HIST_BINS = 8         # colour histogram bins per RGB channel
MIN_HIST_PIXELS = 30  # fewer torso pixels in a view: no histogram there
COLOUR_MARGIN = 0.15  # Hellinger distances this far apart tell two people apart by colour
MIX_BUILD = 0.2       # bone lengths this far (median relative) from the subject's: not the subject (a mix)
BUILD_FRAMES = 25     # the subject's build: the median over this many last frames
BEHIND_M = 0.2       # another person's torso this much farther from a camera than the subject's: behind it
CLEAR_MARGIN = 0.1    # another person's keypoint box grown by this share of its height (their body's outline)
MIN_VIEW_POINTS = 8   # confident keypoints a view keeps clear of the others to count
MIN_POINTS = 12       # keypoints triangulated from the views clear of the others, else the frame is held
MIN_VIEWS_NEAR = 3    # views clear of the others (and agreeing) a frame needs with someone else in view: a
                      # wrong view is outvoted by two (measured: 2 views left put the feet 0.4-0.6 m off)
CLOSE_M = 0.9         # another person's torso this close (on the floor) to the subject's: the frame is held
APART_FRAMES = 3      # frames in a row the subject is seen apart from the others that end a crowded stretch
CLOSE_EXPIRE = 25     # surveyed frames alone that end a crowded stretch (the other person left)
JUMP_CLEAR = 2.0      # a jump (a cut) is re-associated only this far (gate-relative) from every other track
_TORSO = (11, 12, 24, 23)   # BlazePose shoulders and hips, in polygon order


def body_centre(points: np.ndarray, conf: np.ndarray) -> np.ndarray | None:
    """(3,) metres: the mean of the triangulated shoulders and hips (points (K, 3), conf (K,), BlazePose
    order), else the median of every triangulated keypoint; None with fewer than 4 keypoints."""
    ok = np.asarray(conf) > 0
    if ok.sum() < 4:
        return None
    torso = [k for k in _TORSO if k < len(ok) and ok[k]]
    if len(torso) >= 3:
        return np.asarray(points, np.float64)[torso].mean(0)
    return np.median(np.asarray(points, np.float64)[ok], axis=0)


def torso_histograms(images, xy: np.ndarray, conf: np.ndarray, min_conf: float = 0.3) -> list:
    """Per view, the normalised colour histogram ((HIST_BINS^3,) float64) of the pixels inside the
    person's torso (the quadrilateral of shoulders and hips ``xy`` (C, K, 2) pixels, shrunk by 20 %
    towards its centre), or None where those keypoints are not all confident or too few pixels fall
    inside. images: C (H, W, 3) float [0, 1] or uint8."""
    import cv2

    from uvatar.fit.appearance import colour_index

    out = []
    for c, image in enumerate(images):
        if image is None or max(_TORSO) >= conf.shape[1] or (conf[c, list(_TORSO)] < min_conf).any():
            out.append(None)
            continue
        quad = np.asarray(xy[c, list(_TORSO)], np.float64)
        quad = quad.mean(0) + 0.8 * (quad - quad.mean(0))
        mask = np.zeros(np.asarray(image).shape[:2], np.uint8)
        cv2.fillPoly(mask, [np.round(quad).astype(np.int32)], 1)
        inside = mask > 0
        if inside.sum() < MIN_HIST_PIXELS:
            out.append(None)
            continue
        hist = np.bincount(colour_index(image, HIST_BINS)[inside], minlength=HIST_BINS ** 3).astype(np.float64)
        out.append(hist / hist.sum())
    return out


def hist_distance(hists: list, model: np.ndarray | None) -> float:
    """Median over the views with a histogram of the Hellinger distance (0 same, 1 disjoint) between
    each view's histogram and ``model`` (normalised); nan without a model or any histogram."""
    if model is None:
        return float("nan")
    d = [np.sqrt(max(0.0, 1.0 - float(np.sum(np.sqrt(h * model))))) for h in hists if h is not None]
    return float(np.median(d)) if d else float("nan")


@dataclass
class Identity:
    """One person's track: position (3,) metres and velocity (3,) m/frame at ``frame`` (index into
    the fitted frames), and colour counts (summed histograms of the views where nobody overlapped it)."""

    position: np.ndarray
    frame: int
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    colours: np.ndarray | None = None
    builds: list = field(default_factory=list)   # the last signatures (bone lengths) seen
    points: np.ndarray | None = None             # (K, 3) the last keypoints seen (0 where none), metres
    points_conf: np.ndarray | None = None        # (K,)

    @property
    def build(self) -> np.ndarray | None:
        """(B,) the median of the signatures seen (nan where a bone never was), or None."""
        import warnings

        if not self.builds:
            return None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return np.nanmedian(np.stack(self.builds[-BUILD_FRAMES:]), axis=0)

    def unlike(self, signature) -> bool:
        """True when ``signature`` is clearly not this person's build (a mix of two people's
        keypoints stretches bones between them): median relative bone difference over ``MIX_BUILD``."""
        from uvatar.fit.person import same_body

        build = self.build
        if build is None or signature is None or len(self.builds) < 3:
            return False
        d = same_body(signature, build)
        return bool(np.isfinite(d) and d > MIX_BUILD)

    def predict(self, t: int) -> np.ndarray:
        """(3,) where the person is expected at frame ``t`` (the velocity held for at most 5 frames)."""
        steps = float(np.clip(t - self.frame, -5, 5))
        return self.position + self.velocity * steps

    def gate(self, t: int, step_m: float) -> float:
        """Metres a person can have moved from :meth:`predict` at ``t`` (``step_m``: per frame)."""
        return SLACK_M + step_m * max(abs(t - self.frame), 1)

    def score(self, t: int, centre: np.ndarray, step_m: float) -> float:
        """Distance from the prediction over the gate (<= 1: inside)."""
        return float(np.linalg.norm(centre - self.predict(t)) / self.gate(t, step_m))

    def predicted_points(self, t: int) -> tuple[np.ndarray, np.ndarray] | None:
        """((K, 3), (K,)) the last keypoints seen moved to :meth:`predict` at ``t``, or None."""
        if self.points is None:
            return None
        return self.points + (self.predict(t) - self.position), self.points_conf

    def update(self, t: int, centre: np.ndarray, hists: list | None = None, points=None, points_conf=None) -> None:
        if points is not None:
            self.points, self.points_conf = np.asarray(points, np.float64), np.asarray(points_conf, np.float64)
        gap = t - self.frame
        if gap != 0 and abs(gap) <= 3:
            self.velocity = 0.5 * self.velocity + 0.5 * (centre - self.position) / gap
        elif gap != 0:
            self.velocity = np.zeros(3)
        self.position, self.frame = np.asarray(centre, np.float64), t
        for h in hists or ():
            if h is not None:
                self.colours = h.copy() if self.colours is None else self.colours + h

    @property
    def model(self) -> np.ndarray | None:
        return None if self.colours is None else self.colours / self.colours.sum()


@dataclass
class Candidate:
    """A person seen in one frame: centre (3,), histograms per view, the Person (or None for the
    primary observation) it came from."""

    centre: np.ndarray
    hists: list
    person: object = None
    signature: np.ndarray | None = None        # (B,) bone lengths (:func:`~uvatar.fit.person.body_signature`)
    boxes: list = field(default_factory=list)    # per view: (x0, y0, x1, y1) of the confident keypoints, or None
    torsos: list = field(default_factory=list)   # per view: the same box of the torso keypoints, or None
    points: np.ndarray | None = None             # (K, 3) triangulated keypoints, metres
    points_conf: np.ndarray | None = None        # (K,)

    @classmethod
    def of(cls, images, points, points_conf, xy, conf, person=None, min_conf: float = 0.3) -> Candidate | None:
        """From triangulated keypoints (K, 3), (K,) and their detections (C, K, 2), (C, K); None
        with too few keypoints (:func:`body_centre`)."""
        centre = body_centre(points, points_conf)
        if centre is None:
            return None
        xy, conf = np.asarray(xy), np.asarray(conf)

        def box(c, keys):
            ok = keys[conf[c, keys] >= min_conf]
            if len(ok) < 3:
                return None
            lo, hi = xy[c, ok].min(0), xy[c, ok].max(0)
            return (*lo, *hi)

        from uvatar.fit.person import body_signature

        every, torso = np.arange(conf.shape[1]), np.array([k for k in _TORSO if k < conf.shape[1]])
        signature = body_signature(np.asarray(points, np.float64), np.asarray(points_conf)) \
            if len(points_conf) > max(_TORSO) else None
        return cls(centre=centre, hists=torso_histograms(images, xy, conf), person=person, signature=signature,
                   boxes=[box(c, every) for c in range(len(conf))], torsos=[box(c, torso) for c in range(len(conf))],
                   points=np.asarray(points, np.float64), points_conf=np.asarray(points_conf, np.float64))

    def clean_hists(self, others: list[Candidate]) -> list:
        """The histograms of the views where no other person's box overlaps this person's torso."""
        def overlap(a, b):
            return a is not None and b is not None and a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]

        return [None if h is None or any(overlap(self.torsos[c] if c < len(self.torsos) else None,
                                                 o.boxes[c] if c < len(o.boxes) else None) for o in others) else h
                for c, h in enumerate(self.hists)]


class SubjectTracker:
    """Judges each frame's subject observation (see the module doc). ``step_m``: metres a person can
    move per frame (max speed / fps). :meth:`judge` returns (status, the candidate taken or None);
    statuses: "tracked", "reassociated", "lost", "ambiguous"."""

    def __init__(self, step_m: float) -> None:
        self.step_m = float(step_m)
        self.subject: Identity | None = None
        self.others: list[Identity] = []
        self.last_survey: int | None = None
        self.held = False
        self.unassigned: list[Candidate] = []   # this frame's candidates that could be either person
        self.close_since: int | None = None      # another person close since this frame (see _crowded)
        self.alone = self.apart = 0
        self.surveys = 0
        self.others_seen = 0

    def start(self, t: int, centre: np.ndarray, hists: list | None = None) -> None:
        """(Re)start the track at frame ``t`` (the seed frame, a pass's start, a cut)."""
        colours = self.subject.colours if self.subject is not None else None   # the same clothes ...
        builds = self.subject.builds if self.subject is not None else []         # ... and the same build
        self.subject = Identity(position=np.asarray(centre, np.float64), frame=t, colours=colours, builds=builds)
        if hists:
            self.subject.update(t, centre, hists)
        self.others, self.last_survey, self.held = [], None, False
        self.close_since, self.alone, self.apart = None, 0, 0

    def accept(self, t: int, cand: Candidate, hists: list | None) -> None:
        self.subject.update(t, cand.centre, hists, cand.points, cand.points_conf)
        if cand.signature is not None:
            self.subject.builds.append(cand.signature)

    def needs_survey(self, t: int, primary: Candidate | None) -> bool:
        """True when the other people must be looked for at frame ``t``."""
        if self.last_survey is None or abs(t - self.last_survey) >= SURVEY_EVERY or self.held:
            return True
        if primary is None or self.subject.score(t, primary.centre, self.step_m) > 1 \
                or self.subject.unlike(primary.signature):
            return True
        if self._claimed(t, primary.centre) <= 1:
            return True
        here = self.subject.predict(t)
        if any(np.linalg.norm(o.predict(t) - here) < NEAR_M + o.gate(t, self.step_m) for o in self.others):
            return True
        d = hist_distance(primary.hists, self.subject.model)
        return bool(np.isfinite(d) and d > COLOUR_MARGIN * 2)

    def _claimed(self, t: int, centre: np.ndarray) -> float:
        """The smallest gate-relative distance of ``centre`` to another person's track (inf: none)."""
        scores = [o.score(t, centre, self.step_m) for o in self.others if abs(t - o.frame) <= FORGET_FRAMES]
        return min(scores, default=np.inf)

    def judge(self, t: int, primary: Candidate | None, people: list[Candidate] | None) -> tuple[str, Candidate | None]:
        """The subject at frame ``t``: ``primary`` the crop observation's candidate (None: too few
        keypoints), ``people`` everyone found at ``t`` (None: nobody looked). Updates the tracks.

        Every candidate is labelled against the tracks (gate-relative distances ``s`` to the subject's,
        ``o`` to the nearest other one): the subject's (inside its gate, not inside another's unless
        ``DECISIVE``-ly nearer the subject's; after a hold, whose gate has grown, not inside another's
        at all), another's (the reverse), either's (inside both, neither decisive: one of the two, or a
        skeleton made of both) or nobody's. One subject's candidate is taken (two: the nearer when
        decisive, else the colours, else ambiguous); with none, one either's candidate whose colours
        are clearly the subject's rather than the other person's is taken, else the frame is
        ambiguous; with neither, the subject is lost, unless one nobody's candidate has the subject's
        build and colours clearly the subject's rather than every other track's (a jump: a cut to
        another take, re-associated), or nobody else was ever seen (one person in view: a cut). Other
        tracks learn only from candidates that are theirs or nobody's: an either's candidate teaches
        nobody (a track never drifts onto the subject through a mix)."""
        self.unassigned = []
        if people is not None:
            self.last_survey = t
            self.surveys += 1
        if people is None:
            ok = primary is not None and self.subject.score(t, primary.centre, self.step_m) <= 1 \
                and self._claimed(t, primary.centre) > 1 and not self.subject.unlike(primary.signature)
            return self._finish(t, "tracked" if ok else "lost", primary if ok else None, [], [])
        crop = primary
        cands = list(people)
        if primary is not None and not cands:
            cands.append(primary)
        # else a crop observation that is none of the people found is a mix of two people (the detector
        # took one person in some views and the other in the rest): the people found decide
        if not any(c is primary for c in cands) and primary is not None:
            same = [p for p in cands if np.linalg.norm(p.centre - primary.centre) < SLACK_M]
            primary = same[0] if same else None
        s = np.array([self.subject.score(t, c.centre, self.step_m) for c in cands])
        o = np.array([self._claimed(t, c.centre) for c in cands])
        unlike = np.array([self.subject.unlike(c.signature) for c in cands], bool)
        label = []
        for i in range(len(cands)):
            mine = s[i] <= 1 and not unlike[i]
            theirs = o[i] <= 1
            if mine and (not theirs or (not self.held and s[i] <= DECISIVE * o[i])):
                label.append("subject")
            elif theirs and (not mine or o[i] <= DECISIVE * s[i]):
                label.append("other")
            elif mine:
                label.append("either")
            else:
                label.append("nobody")
        label = np.array(label)
        if self.held:   # after a hold (the gates have grown, the tracks stood still): re-association
            i = self._reassociate(t, cands, unlike)
            status, chosen = ("reassociated", cands[i]) if i is not None else (
                "ambiguous" if (s <= 1).any() else "lost", None)
        else:
            status, chosen = "lost", None
            subject = sorted(np.flatnonzero(label == "subject"), key=lambda k: s[k])
            either = np.flatnonzero(label == "either")
            if len(subject) == 1 or (len(subject) > 1 and s[subject[0]] <= DECISIVE * s[subject[1]]):
                status, chosen = "tracked", cands[subject[0]]
            elif len(subject) > 1:
                by_colour = sorted(subject, key=lambda k: hist_distance(cands[k].hists, self.subject.model))
                d0 = hist_distance(cands[by_colour[0]].hists, self.subject.model)
                d1 = hist_distance(cands[by_colour[1]].hists, self.subject.model)
                if np.isfinite(d0) and np.isfinite(d1) and d1 - d0 > COLOUR_MARGIN:
                    status, chosen = "tracked", cands[by_colour[0]]
                else:
                    status = "ambiguous"
            elif len(either):
                by_colour = [k for k in either if self._colour_says(cands[k], self._nearest_other(t, cands[k]))]
                if len(by_colour) == 1 and len(either) == 1:
                    status, chosen = "tracked", cands[by_colour[0]]
                else:
                    status = "ambiguous"
            elif not self.others_seen and not self.others and len(cands) == 1 and not unlike[0]:
                status, chosen = "tracked", cands[0]   # one person in view, nobody else ever seen: a cut or a jump
            else:
                jumped = [k for k in np.flatnonzero(label == "nobody")
                          if not unlike[k] and o[k] > JUMP_CLEAR and self._colour_says_all(t, cands[k])]
                if len(jumped) == 1:
                    status, chosen = "jumped", cands[jumped[0]]
                log.debug("frame %d: a jump? colour distances to the subject %s, to the others %s", t,
                          [round(hist_distance(c.hists, self.subject.model), 2) for c in cands],
                          [[round(hist_distance(c.hists, o.model), 2) for o in self.others] for c in cands])
        log.debug("frame %d: %s; subject scores %s, other-track scores %s, labels %s", t, status,
                  np.round(s, 2).tolist(), np.round(o, 2).tolist(), label.tolist())
        # everyone else in view (a second grouping of the subject's own detections lies within 2 x SLACK_M)
        keep = [i for i, c in enumerate(cands) if c is not chosen and (
            chosen is None or np.linalg.norm(c.centre - chosen.centre) >= 2 * SLACK_M)]
        seen = [cands[i] for i in keep]
        # after a hold, the subject taken back: everyone else apart from it is someone else (their tracks,
        # standing still through the hold, start again from here)
        teach = [cands[i] for i in keep if label[i] in ("other", "nobody") or (
            self.held and chosen is not None and np.linalg.norm((cands[i].centre - chosen.centre)[[0, 2]]) >= CLOSE_M)]
        self.unassigned = [cands[i] for i in keep if label[i] == "either"]
        entering = self.close_since is None
        if (status != "lost" or not entering) and self._crowded(t, chosen, seen):
            if entering:   # the people just come close are tracked from where they were last seen apart
                self._finish(t, "crowded", None, teach, seen, new_people=True)
            self.held, self.unassigned = True, []
            return "crowded", None
        if chosen is not None and crop is not None and np.linalg.norm(chosen.centre - crop.centre) < SLACK_M:
            chosen = crop
        return self._finish(t, status, chosen, teach, seen)

    def _crowded(self, t: int, chosen: Candidate | None, seen: list[Candidate]) -> bool:
        """True when another person is within ``CLOSE_M`` (on the floor) of the subject (``chosen``, or
        where it is predicted): another candidate of ``t``, or another track seen in the last
        ``NEAR_FRAMES`` frames (where it is predicted: one not found at ``t`` may be merged with the
        subject or hidden by it). Once crowded, it stays so, with every track standing still (a
        skeleton there may be a mix of both people, and it would drag a track onto the other person),
        until the subject is seen apart from someone else (taken back, with another candidate and all of
        them farther than ``CLOSE_M``) in ``APART_FRAMES`` frames in a row (a ghost of two people's
        detections paired across views may lie anywhere for a frame), or alone for ``CLOSE_EXPIRE`` surveyed frames (the other one left)."""
        ref = chosen.centre if chosen is not None else self.subject.predict(t)

        def floor(a):
            return float(np.linalg.norm((np.asarray(a) - ref)[[0, 2]]))

        here = [floor(c.centre) for c in seen]
        if self.close_since is not None:
            self.apart = self.apart + 1 if chosen is not None and here and min(here) >= CLOSE_M else 0
            if self.apart >= APART_FRAMES:
                self.close_since, self.alone, self.apart = None, 0, 0
                return False
            self.alone = self.alone + 1 if not here else 0
            if self.alone >= CLOSE_EXPIRE:
                self.close_since, self.alone, self.apart = None, 0, 0
                return False
            return True
        tracks = [floor(o.predict(t)) for o in self.others if abs(t - o.frame) <= NEAR_FRAMES]
        if min(here + tracks, default=np.inf) < CLOSE_M:
            self.close_since, self.alone = t, 0
            return True
        return False

    def _reassociate(self, t: int, cands: list[Candidate], unlike: np.ndarray) -> int | None:
        """After a hold, the index of the candidate taken back as the subject, or None: the one nearest
        where the subject was last seen, inside its (grown) gate, of its build, decisively nearer it
        than any other candidate (``DECISIVE``), nearer it than where any other person was last seen,
        and whose colours are not clearly another person's."""
        if not cands:
            return None
        here = self.subject.predict(t)
        d = np.array([np.linalg.norm(c.centre - here) for c in cands])
        order = np.argsort(d)
        i = int(order[0])
        if d[i] > self.subject.gate(t, self.step_m) or unlike[i]:
            return None
        if len(order) > 1 and d[i] > DECISIVE * d[order[1]]:
            return None
        live = [o for o in self.others if abs(t - o.frame) <= FORGET_FRAMES]
        if any(np.linalg.norm(cands[i].centre - o.position) < d[i] for o in live):
            return None
        if any(self._colour_says_other(cands[i], o) for o in live):
            return None
        return i

    def _colour_says_other(self, cand: Candidate, other: Identity) -> bool:
        """True when the candidate's colours are clearly ``other``'s rather than the subject's."""
        d_s, d_o = hist_distance(cand.hists, self.subject.model), hist_distance(cand.hists, other.model)
        return bool(np.isfinite(d_s) and np.isfinite(d_o) and d_s - d_o > COLOUR_MARGIN)

    def _nearest_other(self, t: int, cand: Candidate) -> Identity | None:
        live = [o for o in self.others if abs(t - o.frame) <= FORGET_FRAMES]
        return min(live, key=lambda o: o.score(t, cand.centre, self.step_m), default=None)

    def _colour_says(self, cand: Candidate, other: Identity | None) -> bool:
        """True when the candidate's colours are clearly the subject's rather than ``other``'s."""
        if other is None:
            return False
        d_s, d_o = hist_distance(cand.hists, self.subject.model), hist_distance(cand.hists, other.model)
        return bool(np.isfinite(d_s) and np.isfinite(d_o) and d_o - d_s > COLOUR_MARGIN)

    def _colour_says_all(self, t: int, cand: Candidate) -> bool:
        """True when the candidate's colours are clearly the subject's rather than those of every other
        person tracked in the last ``FORGET_FRAMES`` frames (at least one, with a colour model)."""
        live = [o for o in self.others if abs(t - o.frame) <= FORGET_FRAMES]
        return bool(live) and all(self._colour_says(cand, o) for o in live)

    def others_near(self, t: int, exclude: Candidate | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
        """[((K, 3), (K,))] the keypoints of everyone else at frame ``t``: the other tracks seen at ``t``
        (where nobody was looked for at ``t``: in the last ``NEAR_FRAMES`` frames, moved to their
        prediction) and the candidates of ``t`` that could have been either person (:meth:`judge`), but
        ``exclude``."""
        recent = 0 if self.last_survey == t else NEAR_FRAMES
        out = [p for o in self.others if abs(t - o.frame) <= recent and (p := o.predicted_points(t)) is not None]
        out += [(c.points, c.points_conf) for c in getattr(self, "unassigned", ()) if c is not exclude
                and c.points is not None]
        return out

    def others_close(self, t: int, exclude: Candidate | None = None) -> list[np.ndarray]:
        """[(3,)] where everyone else may be at frame ``t``: the other tracks seen in the last
        ``NEAR_FRAMES`` frames (their prediction: one not found at ``t`` may be merged with the subject
        or hidden by it) and the candidates of ``t`` that could have been either person, but ``exclude``."""
        out = [o.predict(t) for o in self.others if abs(t - o.frame) <= NEAR_FRAMES]
        return out + [c.centre for c in self.unassigned if c is not exclude]

    def _finish(self, t: int, status: str, chosen: Candidate | None, others: list[Candidate],
                seen: list[Candidate], new_people: bool = False):
        """Update the tracks: ``others`` the people not the subject, ``seen`` everyone in view but the
        subject (their boxes keep the colour models clean: a view where someone overlaps a person's
        torso teaches nothing). A new track is started for someone seen beside the subject, or, with
        ``new_people``, anyone unexplained (the people just come close to the subject)."""
        for c in others:   # the other people's tracks: nearest inside its gate, else a new one
            hists = c.clean_hists([o for o in seen + ([chosen] if chosen is not None else []) if o is not c])
            live = [o for o in self.others if abs(t - o.frame) <= FORGET_FRAMES and o.frame != t]
            best = min(live, key=lambda o: o.score(t, c.centre, self.step_m), default=None)
            if best is not None and best.score(t, c.centre, self.step_m) <= 1:
                best.update(t, c.centre, hists, c.points, c.points_conf)
            elif chosen is not None or new_people:   # someone new beside the subject (held: maybe the subject)
                self.others.append(Identity(position=np.asarray(c.centre, np.float64), frame=t))
                self.others[-1].update(t, c.centre, hists, c.points, c.points_conf)
                self.others_seen += 1
        self.others = [o for o in self.others if abs(t - o.frame) <= FORGET_FRAMES]
        if new_people:
            return status, None
        if chosen is not None:
            if self.held or status == "jumped":
                status = "reassociated"
            self.accept(t, chosen, chosen.clean_hists(seen))
        self.held = chosen is None
        return status, chosen
