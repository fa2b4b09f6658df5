"""mfg-lightning: the Motion Field Generator (Kashyap, Fowlkes, Krichmar) on Lightning + Hydra."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("mfg-lightning")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"
