"""body.json: body model parameters (formats/body.md).

`body_from_dict` / `body_to_dict` are the single definition of the body object; view folders
(body.json beside transforms.json) and avatar.npz (its `body` entry) embed the same dict.
Bone labels are not checked against the rig here (io does not import the body model).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from dlacli.errors import DlaInputError, excerpt, excerpts
from dlacli.io.atomic import atomic_path
from dlacli.io.validate import (
    MAX_ANGLE,
    MAX_DISTANCE,
    as_array,
    as_float,
    as_str,
    check_format,
    check_magnitude,
    dump_json,
    load_json,
    require_keys,
)
from dlacli.types import PHENOTYPE_KEYS, BodyParams

MAX_BONES = 1024  # anny's rig has 104; a pose naming more bones than any rig is refused unread

FORMAT = "dla.body/1"
MODELS = ("anny",)
_KEYS = {"format", "model", "phenotype", "root_rotation", "root_translation", "pose"}


def body_from_dict(d: Any, where: Any) -> BodyParams:
    """Validate a body.json object and build BodyParams; errors name `where` (a file or file:key).

    Required: format, model, phenotype (all six keys, each in [0, 1]). Optional: root_rotation,
    root_translation (default zeros) and pose (default {}, every bone at rest).
    """
    require_keys(d, (), where, "the body")
    check_format(d.get("format"), FORMAT, where)
    require_keys(d, ("model", "phenotype"), where)
    unknown = sorted(set(d) - _KEYS)
    if unknown:
        raise DlaInputError(
            where,
            f"unknown key{'s' if len(unknown) > 1 else ''} {excerpts(unknown)} (allowed: {', '.join(sorted(_KEYS))})",
        )
    model = as_str(d["model"], where, "model")
    if model not in MODELS:
        raise DlaInputError(where, f"model {excerpt(model)} is not supported (supported: {', '.join(MODELS)})")

    pheno = d["phenotype"]
    if not isinstance(pheno, dict):
        raise DlaInputError(where, f"phenotype must be an object with keys {', '.join(PHENOTYPE_KEYS)}")
    missing = [k for k in PHENOTYPE_KEYS if k not in pheno]
    if missing:
        raise DlaInputError(
            where,
            f"phenotype is missing {', '.join(map(repr, missing))} (all of {', '.join(PHENOTYPE_KEYS)} are required)",
        )
    extra = sorted(set(pheno) - set(PHENOTYPE_KEYS))
    if extra:
        raise DlaInputError(
            where,
            f"unknown phenotype key{'s' if len(extra) > 1 else ''} {excerpts(extra)} (allowed: "
            f"{', '.join(PHENOTYPE_KEYS)})",
        )
    phenotype = {}
    for key in PHENOTYPE_KEYS:
        value = as_float(pheno[key], where, f"phenotype.{key}")
        if not 0.0 <= value <= 1.0:
            raise DlaInputError(where, f"phenotype.{key} = {value} is outside [0, 1]")
        phenotype[key] = value

    root_rotation = as_array(d.get("root_rotation", [0.0, 0.0, 0.0]), (3,), where, "root_rotation", np.float64)
    root_translation = as_array(d.get("root_translation", [0.0, 0.0, 0.0]), (3,), where, "root_translation", np.float64)
    check_magnitude(root_rotation, MAX_ANGLE, where, "root_rotation", "rad")
    check_magnitude(root_translation, MAX_DISTANCE, where, "root_translation", "m")

    pose_in = d.get("pose", {})
    if pose_in is None:
        pose_in = {}
    if not isinstance(pose_in, dict):
        raise DlaInputError(where, "pose must be an object mapping bone labels to [3] axis-angle rotations")
    if len(pose_in) > MAX_BONES:
        raise DlaInputError(where, f"pose names {len(pose_in)} bones; a rig dla knows has at most {MAX_BONES}")
    pose = {}
    for label, value in pose_in.items():
        if not label:
            raise DlaInputError(where, "pose has an empty bone label")
        pose[label] = as_array(value, (3,), where, f"pose[{excerpt(label)}]", np.float64)
        check_magnitude(pose[label], MAX_ANGLE, where, f"pose[{excerpt(label)}]", "rad")
    return BodyParams(
        phenotype=phenotype,
        root_rotation=root_rotation,
        root_translation=root_translation,
        pose=pose,
        model=model,
    )


def body_to_dict(body: BodyParams) -> dict[str, Any]:
    """The body.json object for `body` (plain Python floats and lists, JSON-ready)."""
    order = [k for k in PHENOTYPE_KEYS if k in body.phenotype] + [k for k in body.phenotype if k not in PHENOTYPE_KEYS]
    return {
        "format": FORMAT,
        "model": body.model,
        "phenotype": {k: _num(body.phenotype[k]) for k in order},
        "root_rotation": [_num(v) for v in np.asarray(body.root_rotation).reshape(-1)],
        "root_translation": [_num(v) for v in np.asarray(body.root_translation).reshape(-1)],
        "pose": {label: [_num(v) for v in np.asarray(r).reshape(-1)] for label, r in body.pose.items()},
    }


def _num(value: Any) -> Any:
    """A Python float where `value` is numeric; anything else is passed on for the validator to name."""
    if isinstance(value, (bool, np.bool_)):
        return value
    try:
        return float(value)
    except (TypeError, ValueError):
        return value


def read_body(path: str | os.PathLike) -> BodyParams:
    """Read and validate a body.json file."""
    return body_from_dict(load_json(path), Path(path))


def write_body(body: BodyParams, path: str | os.PathLike) -> None:
    """Write `body` as body.json (atomic). An invalid body raises DlaInputError naming "body"."""
    d = body_to_dict(body)
    body_from_dict(d, "body")  # the writer never produces a file its reader rejects
    with atomic_path(path) as tmp:
        tmp.write_text(dump_json(d) + "\n", encoding="utf-8")


def summarize_body(path: str | os.PathLike) -> dict[str, Any]:
    """JSON-able summary of a body.json."""
    path = Path(path)
    body = body_from_dict(load_json(path), path)
    angles = {label: float(np.linalg.norm(r)) for label, r in body.pose.items()}
    largest = max(angles, key=angles.get) if angles else None
    return {
        "kind": "body",
        "format": FORMAT,
        "model": body.model,
        "phenotype": dict(body.phenotype),
        "root_rotation": body.root_rotation.tolist(),
        "root_translation": body.root_translation.tolist(),
        "posed_bones": len(body.pose),
        "largest_rotation": None
        if largest is None
        else {"bone": largest, "degrees": float(np.degrees(angles[largest]))},
    }
