"""dla: Dream, Lift, Animate: one photo of a person to an animatable 3D Gaussian avatar."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("dla")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"
