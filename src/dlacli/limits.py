"""Every default and limit that more than one layer reads, written once (torch-free: the CLI
imports this module to build its options and help texts without loading torch).

A stage reads its defaults from here, and the CLI's options and help texts quote the same names, so
a default changes in one place. Limits bound what a file or an option may ask for (memory and time
follow from them; DESIGN.md section 3, "limits.py").
"""

from __future__ import annotations

# --- Gaussians sampled from an avatar's UV map (DESIGN.md section 1, "Animate")
DEFAULT_GAUSSIANS = 131_072  # the paper's count: 65,536 uniform in UV + 65,536 uniform on the surface
MAX_GAUSSIANS = 32 * DEFAULT_GAUSSIANS  # the most an avatar or an option may ask to be drawn with
DEFAULT_SAMPLE_SEED = 0  # seed of the surface sample points

# --- lift
LIFT_STEPS = 50  # refinement steps of the default lift (0 = mesh unprojection only)
LIFT_RESOLUTION = 256  # side of the UV Gaussian map Z
MAX_LIFT_STEPS = 100_000
MAX_VIEWS = 64  # every view is rendered at every refinement step: memory and time grow with them
