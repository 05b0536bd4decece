"""Every default and limit that more than one layer reads, written once (torch-free: the CLI
imports this module to build its options and help texts without loading torch).

A stage reads its defaults from here, and the CLI's options and help texts quote the same names, so
a default changes in one place. Limits bound what a file or an option may ask for (memory and time
follow from them; docs/architecture.md, "limits.py").
"""

from __future__ import annotations

# --- Gaussians sampled from an avatar's UV map (docs/architecture.md, "The method": Animate)
DEFAULT_GAUSSIANS = 131_072  # the paper's count: 65,536 uniform in UV + 65,536 uniform on the surface
# what the default lift refines with and records: refined at this count, an avatar scores better on
# novel views than refined at DEFAULT_GAUSSIANS, in a third of the time (docs/lift.md "Cost and accuracy")
LIFT_GAUSSIANS = 32_768
MIN_GAUSSIANS = 2  # one UV and one surface sample
MAX_GAUSSIANS = 32 * DEFAULT_GAUSSIANS  # the most an avatar or an option may ask to be drawn with
DEFAULT_SAMPLE_SEED = 0  # seed of the surface sample points
# --gaussians auto (stages/budget.py): the counts it chooses from, and how far below the best score it may stay
BUDGET_LADDER = tuple(1 << k for k in range(12, 19))  # 4,096 ... 262,144
BUDGET_TOLERANCE_DB = 0.2

# --- lift
FIT_STEPS = 150  # optimisation steps of dream's body fit (docs/fit.md: 300 fitted no better)
LANDMARKS = ("lite", "full", "heavy")  # MediaPipe Pose landmark models (dlacli.io.detect; docs/motion.md)
DEFAULT_LANDMARKS = "full"  # the one the mediapipe wheel ships
DEFAULT_PRIOR = "shipped"  # dream's body backend: its completion prior (dlacli.stages.dream.completion; docs/dream.md)
LIFT_STEPS = 40  # refinement steps of the default lift (0 = mesh unprojection only), at LIFT_LR: on held-out
# novel views and poses at least as accurate as the session-3 default (50 steps at 131,072 Gaussians) in half its
# time (docs/lift.md "Cost and accuracy")
LIFT_LR = 0.03  # the refinement's Adam learning rate
LIFT_RESOLUTION = 256  # side of the UV Gaussian map Z
MAX_LIFT_STEPS = 100_000
MAX_LIFT_RESOLUTION = 2048  # side of the largest Z (io/avatar.py's MAX_UNPACKED fits it); least: MIN_IMAGE_SIZE
MIN_VIEW_FALLOFF = 0.05  # |k| below this: the avatar keeps the identity decoder (stages/lift/bake.py, `view_falloff`)
MAX_VIEWS = 64  # every view is rendered at every refinement step: memory and time grow with them

# --- the suffixes of the files dla writes, in the order messages list them (the writers check them,
# the CLI's output options check them while parsing)
USD_SUFFIXES = (".usdc", ".usda", ".usd")
SPLAT_SUFFIXES = (".ply", ".spz", ".splat", ".glb")

# --- seeds (sample points, synthetic subjects, diffusion noise): integers in [0, MAX_SEED]
MAX_SEED = 2**32 - 1  # what numpy's legacy seeding and an avatar's extra.samples.seed take
MAX_TRAIN_SEED = 2**31 - 1  # dla train's seed: a signed 32-bit integer
MAX_SYNTH_SEEDS = 1_000_000  # subjects of one `dla synth --seeds` run

# --- images and videos the commands write
MIN_IMAGE_SIZE = 16  # side of a square image or video frame in pixels (render, previews, synth, UV maps)
MAX_IMAGE_SIZE = 4096
MAX_RENDER_PIXELS = 1 << 30  # all images of one render together (--video keeps them in memory, 4 GiB as RGBA8)
MAX_FPS = 1000.0  # frame rates above this are refused (by every motion reader, native ones too)
MIN_RESAMPLE_FPS = 0.1  # the slowest rate --fps resamples a motion to
MIN_VIDEO_FPS = 1.0  # the slowest frame rate of a video dla writes
# dla motion from-video: the most frames one run reads (after --fps/--start/--end); its per-frame
# results are a few hundred bytes, and the fit works on windows of VIDEO_FIT_WINDOW frames
MAX_VIDEO_FRAMES = 36_000  # 20 minutes at 30 fps
VIDEO_FIT_WINDOW = 240  # frames optimised together (memory of one window: ~0.2 GB)
VIDEO_FIT_STEPS = 400  # optimisation steps per window (synthetic CMU clip 131_01: 300 56 mm, 400 54 mm, 500 52 mm)

# --- animate: pose_avatar holds positions, rotations and scales of every frame (40 bytes a
# Gaussian-frame): 2^27 of them is ~5 GB, e.g. DEFAULT_GAUSSIANS x 1,024 frames
MAX_GAUSSIAN_FRAMES = 1 << 27

# --- dla bench
BENCH_SEED = 1001  # the first synthetic subject of a benchmark (a seed no test uses)
BENCH_IMAGE_SIZE = 512  # the paper's protocol: subjects rendered and scored at 512 x 512, on black
MIN_BENCH_IMAGE_SIZE = 32
MAX_LIST_CHARS = 10_000  # the text of a comma-separated option (--methods, --seeds, --counts, ...)
MAX_LIST_ITEMS = 64  # numbers in one comma-separated option
