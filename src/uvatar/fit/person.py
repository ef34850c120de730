"""Which person to fit when more than one is in view (``uvatar fit --person``).

BlazePose finds one person per image. :func:`find_people` finds several in one frame: in each view
the detector runs, the person found is painted over (the box around their keypoints, in the image's
median colour) and it runs again, up to ``max_people`` times; the per-view detections are then
matched across views by triangulation (two views propose a 3D person, every other view joins with
the detection that reprojects onto it, within ``MATCH_FRACTION`` of that detection's height), giving
3D people, each seen by a set of views (two proposals closer than ``SAME_PERSON_M`` are one person).
:func:`choose_person` picks the subject by a :class:`PersonChoice`:

- ``most-views`` (default): the person seen by the most cameras (ties: the nearest to the centre of
  the capture volume, where a studio puts its subject);
- ``largest``: the largest mean box (pixels^2) over the views that see the person;
- ``centre``: nearest to the centre of the capture volume (the point closest to every camera's
  optical axis);
- ``nearest-to:X,Y,Z``: nearest to a world point (metres);
- ``box:CAM:FRAME:X0,Y0,X1,Y1`` / ``point:CAM:FRAME:X,Y``: the person detected inside that box (or
  around that point) of camera CAM at frame FRAME (pixels);
- ``all``: the subject (as ``most-views``) and every other person seen by two views, each fitted on
  its own (``people/<id>/``, ids 1, 2, ... by the views that see them);
- ``ID`` (a whole number >= 1): that other person alone.

The chosen person's 3D keypoints seed the track (:func:`uvatar.fit.observe.observe_frame`'s prior).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from uvatar.errors import InputError

__all__ = ["PERSON_RULES", "PersonChoice", "Person", "parse_person", "find_people", "choose_person",
           "body_signature", "same_body", "same_place"]

# BlazePose keypoint pairs whose 3D distances describe a body's build (shoulders, hips, upper arms,
# forearms, thighs, shins): the same person keeps them whatever the pose, another person does not
_SIGNATURE_BONES = ((11, 12), (23, 24), (11, 13), (12, 14), (13, 15), (14, 16), (23, 25), (24, 26), (25, 27),
                    (26, 28), (11, 23), (12, 24))
SAME_BODY = 0.12  # median relative difference of the bone lengths below which two bodies are the same

PERSON_RULES = ("most-views", "largest", "centre", "nearest-to", "box", "point", "all", "id")
MATCH_FRACTION = 0.1    # a view joins a 3D person when its detection lies within this x its box height
SAME_PERSON_M = 0.3     # two 3D people whose keypoints lie this close (median, metres) are one


@dataclass(frozen=True)
class PersonChoice:
    """rule: one of :data:`PERSON_RULES`; camera, frame: where a box/point was given; box (x0, y0,
    x1, y1) pixels; target (3,) world metres for ``nearest-to``; person_id: the other person's id
    for ``id``."""

    rule: str = "most-views"
    camera: str | None = None
    frame: str | None = None
    box: tuple[float, float, float, float] | None = None
    target: tuple[float, float, float] | None = None
    person_id: str | None = None

    @property
    def several(self) -> bool:
        """True for ``all`` and ``id``: people other than the subject are fitted."""
        return self.rule in ("all", "id")


def _numbers(text: str, count: int, spec: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != count or not all(np.isfinite(values)):
        raise InputError("person", f"{spec!r}: expected {count} comma-separated numbers after the last ':'")
    return values


def parse_person(spec: str) -> PersonChoice:
    """``--person`` text -> :class:`PersonChoice` (one-line :class:`InputError` on a bad spec)."""
    spec = (spec or "most-views").strip()
    rule, _, rest = spec.partition(":")
    if rule in ("most-views", "largest", "centre", "center", "all") and not rest:
        return PersonChoice(rule="centre" if rule == "center" else rule)
    if rule.isdigit() and not rest:
        if int(rule) < 1:
            raise InputError("person", f"{spec!r}: a person id is >= 1 (the subject is fitted without one)")
        return PersonChoice(rule="id", person_id=str(int(rule)))
    if rule == "nearest-to":
        return PersonChoice(rule=rule, target=_numbers(rest, 3, spec))
    if rule in ("box", "point"):
        parts = rest.split(":")
        if len(parts) != 3 or not parts[0] or not parts[1]:
            raise InputError("person", f"{spec!r}: expected {rule}:CAMERA:FRAME:" +
                             ("X0,Y0,X1,Y1" if rule == "box" else "X,Y"))
        cam, frame = parts[0], parts[1]
        if rule == "box":
            x0, y0, x1, y1 = _numbers(parts[2], 4, spec)
            if x1 <= x0 or y1 <= y0:
                raise InputError("person", f"{spec!r}: the box must have x1 > x0 and y1 > y0")
            return PersonChoice(rule=rule, camera=cam, frame=frame, box=(x0, y0, x1, y1))
        x, y = _numbers(parts[2], 2, spec)
        return PersonChoice(rule=rule, camera=cam, frame=frame, box=(x, y, x, y))
    raise InputError("person", f"{spec!r}: expected one of most-views, largest, centre, nearest-to:X,Y,Z, "
                     "box:CAM:FRAME:X0,Y0,X1,Y1, point:CAM:FRAME:X,Y, all, or a person id (1, 2, ...)")


@dataclass
class Person:
    """A person found in one frame: points (K, 3) metres, points_conf (K,), members {camera index:
    detection index}, detections {camera index: (xy (K, 2), conf (K,))} of the members,
    reprojection_px: mean over the used keypoints."""

    points: np.ndarray
    points_conf: np.ndarray
    members: dict = field(default_factory=dict)
    detections: dict = field(default_factory=dict)
    reprojection_px: float = 0.0

    def box(self, c: int, min_conf: float = 0.3):
        """(x0, y0, x1, y1) of the person's confident keypoints in view c, or None."""
        xy, conf = self.detections[c]
        return _keypoint_box(xy, conf, min_conf)


def _keypoint_box(xy, conf, min_conf: float = 0.3):
    ok = conf >= min_conf
    if ok.sum() < 4:
        return None
    lo, hi = xy[ok].min(0), xy[ok].max(0)
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def _view_detections(image, detector, max_people: int, roi=None) -> list:
    """Up to ``max_people`` detections (xy, conf) in one image, each painted over before the next."""
    img = np.array(image, np.float32, copy=True)
    fill = np.median(img.reshape(-1, img.shape[-1]), axis=0)
    out = []
    for _ in range(max_people):
        det = detector.detect(img, roi=roi)
        box = _keypoint_box(det.xy, det.conf)
        if box is None:
            break
        out.append((det.xy.astype(np.float64), det.conf.astype(np.float64)))
        x0, y0, x1, y1 = box
        pad_x, pad_y = 0.2 * (x1 - x0) + 4, 0.12 * (y1 - y0) + 4
        H, W = img.shape[:2]
        r0, r1 = int(max(y0 - pad_y, 0)), int(min(y1 + pad_y, H))
        c0, c1 = int(max(x0 - pad_x, 0)), int(min(x1 + pad_x, W))
        img[r0:r1, c0:c1] = fill
        if roi is not None:
            break  # a box names one person
    return out


def find_people(images, cameras, detector, triangulate_config, max_people: int = 3,
                forced: dict | None = None) -> list[Person]:
    """The people in one frame (images: C (H, W, 3) float32; cameras: C cameras), most views first.

    forced: {camera index: roi} views whose only detection is the one inside that box."""
    from uvatar.fit.projection import project_distorted
    from uvatar.fit.triangulate import triangulate

    forced = forced or {}
    C = len(cameras)
    dets = [_view_detections(images[c], detector, 1 if c in forced else max_people, forced.get(c))
            for c in range(C)]
    K = len(detector.keypoint_names)

    def solve(members: dict):
        xy = np.zeros((C, K, 2))
        conf = np.zeros((C, K))
        for c, i in members.items():
            xy[c], conf[c] = dets[c][i]
        return triangulate(xy, conf, cameras, triangulate_config), xy, conf

    hypotheses = []
    for a in range(C):
        for b in range(a + 1, C):
            for i in range(len(dets[a])):
                for j in range(len(dets[b])):
                    tri, _, _ = solve({a: i, b: j})
                    if (tri.conf > 0).sum() < 6:
                        continue
                    members = {a: i, b: j}
                    ok = tri.conf > 0
                    for c in range(C):
                        if c in members:
                            continue
                        pix, z = project_distorted(cameras[c], tri.points[ok])
                        best, best_err = None, np.inf
                        for n, (xy, conf) in enumerate(dets[c]):
                            seen = conf[ok] >= triangulate_config.min_conf
                            if seen.sum() < 4:
                                continue
                            tol = MATCH_FRACTION * np.ptp(xy[ok][seen][:, 1])
                            err = float(np.median(np.linalg.norm(pix[seen] - xy[ok][seen], axis=1)))
                            err = err if err < tol else np.inf
                            if err < best_err:
                                best, best_err = n, err
                        if best is not None:
                            members[c] = best
                    tri, xy, conf = solve(members)
                    rep = tri.reprojection_px[np.isfinite(tri.reprojection_px)]
                    hypotheses.append((len(members), -(float(rep.mean()) if rep.size else 1e9), members, tri))
    hypotheses.sort(key=lambda h: (h[0], h[1]), reverse=True)
    people, taken = [], set()
    for _, neg_rep, members, tri in hypotheses:
        if any((c, i) in taken for c, i in members.items()):
            # a detection already taken (one taking two people, as where one stands in front of the
            # other) is left to that person; the rest of the views may still be someone else
            members = {c: i for c, i in members.items() if (c, i) not in taken}
            if len(members) < 2:
                continue
            tri, _, _ = solve(members)
            if (tri.conf > 0).sum() < 6:
                continue
            rep = tri.reprojection_px[np.isfinite(tri.reprojection_px)]
            neg_rep = -(float(rep.mean()) if rep.size else 1e9)
        taken.update(members.items())
        if any(same_place(p.points, p.points_conf, tri.points, tri.conf) for p in people):
            continue  # the same person from other views (detections the matching left apart)
        people.append(Person(points=tri.points.astype(np.float64), points_conf=tri.conf.astype(np.float64),
                             members=dict(members), detections={c: dets[c][i] for c, i in members.items()},
                             reprojection_px=-neg_rep))
    return people


def same_place(a, ca, b, cb) -> bool:
    """True when two triangulated keypoint sets (K, 3) metres with confidences (K,) are one person:
    their shared keypoints (>= 4) lie within ``SAME_PERSON_M`` of each other (median)."""
    both = (ca > 0) & (cb > 0)
    return bool(both.sum() >= 4 and np.median(np.linalg.norm(a[both] - b[both], axis=1)) < SAME_PERSON_M)


def body_signature(points: np.ndarray, conf: np.ndarray) -> np.ndarray:
    """(B,) metres: the lengths of :data:`_SIGNATURE_BONES` (nan where an end is not triangulated)."""
    a, b = np.array(_SIGNATURE_BONES).T
    ok = (conf[a] > 0) & (conf[b] > 0)
    return np.where(ok, np.linalg.norm(points[a] - points[b], axis=-1), np.nan)


def same_body(sig_a: np.ndarray, sig_b: np.ndarray) -> float:
    """Median relative difference of two :func:`body_signature` (inf with fewer than 4 bones in both)."""
    both = np.isfinite(sig_a) & np.isfinite(sig_b)
    if both.sum() < 4:
        return np.inf
    return float(np.median(np.abs(sig_a[both] - sig_b[both]) / np.maximum(sig_b[both], 1e-6)))


def volume_centre(cameras) -> np.ndarray:
    """(3,) the world point closest (least squares) to every camera's optical axis."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for cam in cameras:
        centre = -cam.R.T @ cam.T
        d = cam.R[2] / np.linalg.norm(cam.R[2])
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ centre
    return np.linalg.lstsq(A, b, rcond=None)[0]


def _position(p: Person) -> np.ndarray:
    ok = p.points_conf > 0
    return np.median(p.points[ok], axis=0) if ok.any() else np.zeros(3)


def choose_person(people: list[Person], choice: PersonChoice, cameras) -> tuple[int, str]:
    """(index into ``people``, a sentence saying why). Raises :class:`InputError` when nobody fits."""
    if not people:
        raise InputError("person", "no person is seen by two views in the frame the choice is made at")
    rule = "most-views" if choice.several else choice.rule
    if rule == "most-views":
        most = max(len(p.members) for p in people)
        tied = [i for i, p in enumerate(people) if len(p.members) == most]
        centre = volume_centre(cameras)
        i = min(tied, key=lambda k: float(np.linalg.norm(_position(people[k]) - centre)))
        tie = f", the nearest of {len(tied)} to the capture volume's centre" if len(tied) > 1 else ""
        return i, f"seen by the most cameras ({most} of {len(cameras)}){tie}"
    if rule == "largest":
        def area(p):
            boxes = [p.box(c) for c in p.members]
            return np.mean([(b[2] - b[0]) * (b[3] - b[1]) for b in boxes if b is not None] or [0.0])
        i = int(np.argmax([area(p) for p in people]))
        return i, f"largest in the images ({area(people[i]):.0f} px^2 mean box)"
    if rule in ("centre", "nearest-to"):
        target = volume_centre(cameras) if rule == "centre" else np.asarray(choice.target, np.float64)
        d = [float(np.linalg.norm(_position(p) - target)) for p in people]
        i = int(np.argmin(d))
        return i, f"nearest to {np.round(target, 2).tolist()} ({d[i]:.2f} m)"
    names = [c.name for c in cameras]
    c = names.index(choice.camera)
    x0, y0, x1, y1 = choice.box
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    best, best_d = None, np.inf
    for i, p in enumerate(people):
        if c not in p.members:
            continue
        box = p.box(c)
        if box is None:
            continue
        inside = box[0] <= centre[0] <= box[2] and box[1] <= centre[1] <= box[3]
        d = np.linalg.norm(centre - [(box[0] + box[2]) / 2, (box[1] + box[3]) / 2]) - (1e6 if inside else 0)
        if d < best_d:
            best, best_d = i, d
    if best is None:
        raise InputError("person", f"nobody seen by another camera matches the {rule} in {choice.camera} "
                         f"at frame {choice.frame}")
    return best, f"the person at the {rule} given in {choice.camera}, frame {choice.frame}"
