"""rigctl: run magnetic micro-robot manipulation rigs."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("rigctl")
except PackageNotFoundError:  # a checkout that was never installed
    __version__ = "0+unknown"
