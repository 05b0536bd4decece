"""`load_motion(spec)`: any motion the toolkit accepts, as a native Motion on anny's rig.

A spec is one of (checked in this order):
- a path to a native motion.npz (`format` = "dla.motion/1");
- a path to an AMASS .npz (has a `poses` array);
- a path to a .bvh file;
- a path to an .amc file: its ASF skeleton is found beside it (`dlacli.io.asf_amc.find_asf`),
  or named explicitly as "CLIP.amc:SUBJECT.asf" (or with the `asf` argument);
- a built-in motion name: idle, walk, turnaround, wave.
A built-in name is the built-in motion even when a file of that name (with no suffix, so never
a motion file dla reads) lies in the current folder; `./walk.bvh` and other paths with a suffix
are always files. Third-party motions are retargeted (`dlacli.body.retarget`); `fps`
resamples the result; `allow_missing_joints` lets a file lacking joints its naming family
always has (a renamed LeftUpLeg, a cut AMASS layout) through, with those anny bones at rest.

A stage (not part of `dlacli.body`): it reads files through `dlacli.io` and retargets them with
`dlacli.body`, and only a layer above both may use both (docs/architecture.md, "The layers").
"""

from __future__ import annotations

import os
from pathlib import Path

from dlacli.body.builtin_motions import BUILTINS, builtin_motion
from dlacli.errors import DlaInputError
from dlacli.types import Motion

SUFFIXES = (".npz", ".bvh", ".amc")


def split_spec(spec: str) -> tuple[Path, Path | None]:
    """(motion path, explicit ASF path or None) from a spec string."""
    path = Path(spec)
    if not path.exists() and ":" in spec:
        left, right = spec.rsplit(":", 1)
        if left.lower().endswith(".amc") and right.lower().endswith(".asf"):
            return Path(left), Path(right)
    return path, None


def load_motion(
    spec: str | os.PathLike,
    *,
    fps: float | None = None,
    asf: str | os.PathLike | None = None,
    phenotype: dict[str, float] | None = None,
    allow_missing_joints: bool = False,
) -> Motion:
    """Load and (for third-party files) retarget a motion; see the module docstring.

    `phenotype` is the body the retargeting scales the root path for (default body if None).
    Bad input raises DlaInputError naming the file (or spec) and the problem.
    """
    spec = str(spec)
    path, asf_path = split_spec(spec)
    if asf is not None:
        asf_path = Path(asf)
    if not path.exists() or (spec in BUILTINS and not path.suffix):
        if spec in BUILTINS:
            motion = builtin_motion(spec)
            return motion if fps is None else _resample(motion, fps)
        raise DlaInputError(spec, f"no such file, and not a built-in motion ({', '.join(BUILTINS)})")
    if path.is_dir():
        raise DlaInputError(path, "is a folder; expected a motion file (.npz, .bvh, .amc)")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        from dlacli.io.validate import npz_format

        if npz_format(path) != "amass":  # a dla motion (read_motion checks the version)
            from dlacli.io.motion import read_motion

            motion = read_motion(path)
            _check_rig_labels(motion, path)
            return motion if fps is None else _resample(motion, fps)
        from dlacli.io.amass import read_amass

        skel = read_amass(path)
    elif suffix == ".bvh":
        from dlacli.io.bvh import read_bvh

        skel = read_bvh(path)
    elif suffix == ".amc":
        from dlacli.io.asf_amc import find_asf, read_amc

        if asf_path is None:
            asf_path = find_asf(path)
        elif not asf_path.is_file():
            raise DlaInputError(asf_path, "no such ASF skeleton file")
        skel = read_amc(path, asf_path)
    elif suffix == ".asf":
        raise DlaInputError(
            path, "an ASF file holds a skeleton only; give its AMC motion (CLIP.amc or CLIP.amc:SUBJECT.asf)"
        )
    else:
        raise DlaInputError(
            path, f"unsupported motion file type {path.suffix!r} (expected {', '.join(SUFFIXES)} or a built-in name)"
        )

    from dlacli.body.retarget import anny_rig, retarget

    motion = retarget(skel, anny_rig(phenotype), allow_missing=allow_missing_joints)
    return motion if fps is None else _resample(motion, fps)


def _resample(motion: Motion, fps: float) -> Motion:
    from dlacli.body.retarget import resample_motion

    return resample_motion(motion, float(fps))


def _check_rig_labels(motion: Motion, path: Path) -> None:
    """A native motion drives anny's bones by label: every label must be one of the rig's."""
    from dlacli.body.model import get_body_model

    rig = set(get_body_model().bone_labels)
    unknown = [label for label in motion.bone_labels if label not in rig]
    if unknown:
        more = f" and {len(unknown) - 3} more" if len(unknown) > 3 else ""
        raise DlaInputError(
            path,
            f"bone_labels holds {', '.join(map(repr, unknown[:3]))}{more}, not bones of anny's rig "
            "(convert third-party motions with dla motion convert)",
        )
