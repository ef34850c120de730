"""Skeleton naming: a registry of common rigs, side detection, and matching a skeleton's joints
onto the semantic joints that retargeting uses.

Semantic joints: ``pelvis spine1 spine2 spine3 neck head`` and, per side (``l_``/``r_``),
``collar shoulder elbow wrist hip knee ankle toe`` (``shoulder`` is the upper-arm joint, ``hip``
the thigh joint). A name is normalised by dropping namespaces (``mixamorig:``, ``Armature|``,
``Bip01 ``), splitting off its side (``Left…``/``left_``/``L_``/``l_``/``…_L``/``….L``/``…Left``/
CMU's ``LHipJoint``) and keeping lowercase letters and digits: ``UpperLeg_L`` → (l, ``upperleg``).
Each :class:`Rig` lists the normalised names it uses; the rig matching most joints wins, and
other rigs' names fill what it leaves. The spine is matched by structure: the joints between the
pelvis and the neck become spine1 (lowest), spine2 (middle) and spine3 (highest).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

CENTRAL = ("pelvis", "spine1", "spine2", "spine3", "neck", "head")
LIMB = ("collar", "shoulder", "elbow", "wrist", "hip", "knee", "ankle", "toe")
SEMANTIC_JOINTS = CENTRAL + tuple(f"{s}_{k}" for s in "lr" for k in LIMB)
REQUIRED = ("pelvis", "l_hip", "l_knee", "l_ankle", "r_hip", "r_knee", "r_ankle")


@dataclass(frozen=True)
class Rig:
    """name; central: normalised name → pelvis | spine | neck | head; limb: normalised name
    (side removed) → one of :data:`LIMB`."""

    name: str
    central: dict[str, str]
    limb: dict[str, str]


def _spines(*names: str) -> dict[str, str]:
    return {n: "spine" for n in names}


RIGS = (
    Rig("cmu", {"hips": "pelvis", **_spines("lowerback", "spine", "spine1"), "neck": "neck", "neck1": "neck",
                "head": "head"},
        {"shoulder": "collar", "arm": "shoulder", "forearm": "elbow", "hand": "wrist", "upleg": "hip",
         "leg": "knee", "foot": "ankle", "toebase": "toe"}),
    Rig("mixamo", {"hips": "pelvis", **_spines("spine", "spine1", "spine2"), "neck": "neck", "head": "head"},
        {"shoulder": "collar", "arm": "shoulder", "forearm": "elbow", "hand": "wrist", "upleg": "hip",
         "leg": "knee", "foot": "ankle", "toebase": "toe"}),
    Rig("smpl", {"pelvis": "pelvis", **_spines("spine1", "spine2", "spine3"), "neck": "neck", "head": "head"},
        {"collar": "collar", "shoulder": "shoulder", "elbow": "elbow", "wrist": "wrist", "hip": "hip",
         "knee": "knee", "ankle": "ankle", "foot": "toe"}),
    Rig("unreal", {"pelvis": "pelvis", **_spines("spine01", "spine02", "spine03", "spine04", "spine05"),
                   "neck01": "neck", "neck02": "neck", "head": "head"},
        {"clavicle": "collar", "upperarm": "shoulder", "lowerarm": "elbow", "hand": "wrist", "thigh": "hip",
         "calf": "knee", "foot": "ankle", "ball": "toe"}),
    Rig("unity", {"hips": "pelvis", **_spines("spine", "chest", "upperchest"), "neck": "neck", "head": "head"},
        {"shoulder": "collar", "upperarm": "shoulder", "lowerarm": "elbow", "hand": "wrist", "upperleg": "hip",
         "lowerleg": "knee", "foot": "ankle", "toes": "toe", "toe": "toe"}),
    Rig("rokoko", {"hips": "pelvis", **_spines("spine1", "spine2", "spine3", "spine4"), "neck": "neck", "head": "head"},
        {"shoulder": "collar", "arm": "shoulder", "forearm": "elbow", "hand": "wrist", "thigh": "hip",
         "shin": "knee", "foot": "ankle", "toe": "toe"}),
    Rig("biped", {"pelvis": "pelvis", **_spines("spine", "spine1", "spine2", "spine3"), "neck": "neck",
                  "head": "head"},
        {"clavicle": "collar", "upperarm": "shoulder", "forearm": "elbow", "hand": "wrist", "thigh": "hip",
         "calf": "knee", "foot": "ankle", "toe0": "toe"}),
    Rig("makehuman", {"root": "pelvis", **_spines("spine05", "spine04", "spine03", "spine02", "spine01"),
                      "neck01": "neck", "neck02": "neck", "head": "head"},
        {"clavicle": "collar", "upperarm01": "shoulder", "lowerarm01": "elbow", "wrist": "wrist",
         "upperleg01": "hip", "lowerleg01": "knee", "foot": "ankle", "toe31": "toe"}),
)
RIG_NAMES = tuple(r.name for r in RIGS)
#: Distinct semantic joints (the pelvis among them) a skeleton's names must match for it to be called a rig.
MIN_RIG_JOINTS = 8

_NAMESPACE = re.compile(r"^.*[:|]")
_BIPED = re.compile(r"^bip0*1[\s_]*", re.IGNORECASE)
_SIDE_PATTERNS = (
    re.compile(r"^(?P<s>Left|Right)(?=[A-Z0-9_.\s-])"),
    re.compile(r"^(?P<s>left|right)(?=[A-Z0-9_.\s-])"),
    re.compile(r"^(?P<s>[LRlr])[_.\s-]+"),
    re.compile(r"[_.\s-]+(?P<s>[LRlr])$"),
    re.compile(r"[_.\s-]*(?P<s>Left|Right|left|right)$"),
    re.compile(r"^(?P<s>[LR])(?=[A-Z][a-z])"),
)


def split_side(name: str) -> tuple[str | None, str]:
    """A joint name → (side "l" | "r" | None, normalised base name)."""
    core = _BIPED.sub("", _NAMESPACE.sub("", name.strip()))
    side = None
    for pattern in _SIDE_PATTERNS:
        m = pattern.search(core)
        if m and len(core) > len(m.group(0)):
            side = m.group("s")[0].lower()
            core = core[: m.start()] + core[m.end():]
            break
    return side, re.sub(r"[^a-z0-9]", "", core.lower())


@dataclass
class RigMatch:
    """rig: the recognised rig's name; mapping: source joint → semantic joint; unmapped: source
    joints left out; missing: semantic joints nobody maps to; missing_required: the ones
    retargeting cannot do without; user: the entries that came from a user map."""

    rig: str
    mapping: dict[str, str]
    unmapped: list[str]
    missing: list[str]
    missing_required: list[str]
    user: dict[str, str] = field(default_factory=dict)

    def summary(self) -> dict:
        return {"rig": self.rig, "mapped": dict(self.mapping), "unmapped_joints": list(self.unmapped),
                "missing_semantic_joints": list(self.missing), "missing_required": list(self.missing_required)}


def _rig_candidates(rig: Rig, names, sides) -> dict[str, str]:
    """source joint → semantic class ("pelvis", "spine", "neck", "head", "l_knee", ...)."""
    out = {}
    for n in names:
        side, base = sides[n]
        if side is None and base in rig.central:
            out[n] = rig.central[base]
        elif side is not None and base in rig.limb:
            out[n] = f"{side}_{rig.limb[base]}"
    return out


def _ancestors(parents, j: int) -> list[int]:
    out = []
    while parents[j] >= 0:
        j = int(parents[j])
        out.append(j)
    return out


def _assign(names, parents, candidates: dict[str, str], fill: list[dict[str, str]],
            fixed: dict[str, str | None]) -> dict[str, str]:
    index = {n: i for i, n in enumerate(names)}
    mapping: dict[str, str] = {n: s for n, s in fixed.items() if s}
    taken: set[str] = set(mapping.values())
    for table in [candidates, *fill]:  # first come (tree order) first served
        for n in names:
            sem = table.get(n)
            if sem and sem != "spine" and sem not in taken and n not in mapping and n not in fixed:
                mapping[n] = sem
                taken.add(sem)
    by_sem = {s: index[n] for n, s in mapping.items()}
    chain: list[int] = []
    if "pelvis" in by_sem:  # the spine by structure: the joints between the pelvis and the neck
        top = by_sem.get("neck", by_sem.get("head"))
        if top is None:
            collars = [by_sem[s] for s in ("l_collar", "r_collar", "l_shoulder", "r_shoulder") if s in by_sem]
            top = collars[0] if collars else None
        up = _ancestors(parents, top) if top is not None else []
        if by_sem["pelvis"] in up:
            chain = [j for j in reversed(up[: up.index(by_sem["pelvis"])])
                     if names[j] not in mapping and names[j] not in fixed]
    if not chain:  # no neck above the pelvis: the joints named like a spine, in tree order
        chain = [index[n] for n in names if n not in mapping and n not in fixed
                 and any(t.get(n) == "spine" for t in [candidates, *fill])]
    if chain and not taken & {"spine1", "spine2", "spine3"}:
        slots = {1: ["spine1"], 2: ["spine1", "spine3"]}.get(len(chain), ["spine1", "spine2", "spine3"])
        picks = {1: [chain[0]], 2: [chain[0], chain[-1]]}.get(len(slots), [chain[0], chain[len(chain) // 2], chain[-1]])
        for j, sem in zip(picks, slots, strict=True):
            mapping[names[j]] = sem
    return mapping


def match_rig(names, parents, user_map: dict | None = None, target_names=None) -> RigMatch:
    """Match a skeleton (names (J,), parents (J,)) onto the semantic joints.

    user_map: source joint → semantic joint (or a target body joint name listed in
    ``target_names``: {target joint name: semantic}), or None/"" to leave a joint out; it
    overrides the automatic match. Unknown names in it raise ValueError naming them."""
    names = tuple(names)
    parents = np.asarray(parents)
    sides = {n: split_side(n) for n in names}
    scored = [(len(_rig_candidates(r, names, sides)), -k, r) for k, r in enumerate(RIGS)]
    best = max(scored, key=lambda x: x[:2])[2]
    candidates = _rig_candidates(best, names, sides)
    # a rig is named only for a body: a few joints that happen to share a rig's names ("root", "head")
    # are no MakeHuman skeleton
    human = len(set(candidates.values())) >= MIN_RIG_JOINTS and "pelvis" in candidates.values()
    rig_name = best.name if candidates and human else "unknown"
    fill = [_rig_candidates(r, names, sides) for r in RIGS if r is not best]
    user: dict[str, str | None] = {}
    if user_map:
        unknown = [k for k in user_map if k not in names]
        if unknown:
            raise ValueError(f"the map names joints the skeleton does not have: {', '.join(map(str, unknown[:8]))}")
        to_sem = dict(target_names or {})
        for src, value in user_map.items():
            sem = to_sem.get(value, value) if value else None
            if sem is not None and sem not in SEMANTIC_JOINTS:
                raise ValueError(f"the map sends {src!r} to {value!r}, which is neither a semantic joint "
                                 f"({', '.join(SEMANTIC_JOINTS)}) nor a joint of the target body")
            user[src] = sem
        rig_name = f"{rig_name} + user map"
    mapping = _assign(names, parents, candidates, fill, user)
    missing = [s for s in SEMANTIC_JOINTS if s not in mapping.values()]
    return RigMatch(rig=rig_name, mapping=mapping, unmapped=[n for n in names if n not in mapping], missing=missing,
                    missing_required=[s for s in REQUIRED if s in missing],
                    user={k: v for k, v in user.items() if v})


def read_joint_map(path) -> dict:
    """A ``--map`` file (JSON or YAML: {source joint: semantic or body joint}) → dict."""
    import json
    from pathlib import Path

    from uvatar.errors import InputError

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "joint map file is missing")
    text = path.read_text(errors="replace")
    try:
        if path.suffix.lower() in (".yml", ".yaml"):
            import yaml

            data = yaml.safe_load(text)
        else:
            data = json.loads(text)
    except Exception as exc:  # json.JSONDecodeError, yaml.YAMLError
        raise InputError(path, f"not valid {'YAML' if path.suffix.lower() in ('.yml', '.yaml') else 'JSON'} "
                               f"({type(exc).__name__})") from None
    if not isinstance(data, dict) or not all(isinstance(k, str) and (v is None or isinstance(v, str))
                                             for k, v in data.items()):
        raise InputError(path, "a joint map is an object {source joint: semantic or body joint (or null)}")
    return data
