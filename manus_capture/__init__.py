"""manus-capture: multi-view hand-object grasp capture, from rig to contact maps."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("manus-capture")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"
