"""The package version, in a leaf module that the rest of the package imports (importing
it from the package root would run ``hdrmerge_cli/__init__.py``, whose lazy API import
closes a cycle).  pyproject.toml holds the number; this reads the installed metadata."""
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("hdrmerge-cli")
except PackageNotFoundError:  # running from a source tree without installing
    __version__ = "0.0.0+source"
