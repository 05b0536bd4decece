"""dla: Dream, Lift, Animate: one photo of a person to an animatable 3D Gaussian avatar."""

import os
from importlib.metadata import PackageNotFoundError, version

# numba's and torch's OpenMP thread pools busy-wait by default and starve each other on small
# machines (a 2k-Gaussian render took 50 ms instead of 3 ms on 2 cores); set before torch loads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

try:
    __version__ = version("dla")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"
