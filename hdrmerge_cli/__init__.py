"""hdrmerge-cli: noise-optimal HDR merging of exposure brackets.

Implements Goossens, Luong, Aelterman, Pizurica, Philips, "Realistic camera noise
modeling with application to improved HDR synthesis", EURASIP J. Adv. Signal Process.
2012:171 ("the paper"; equations cited as (N)).
"""
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("hdrmerge-cli")
except PackageNotFoundError:  # running from a source tree without installing
    __version__ = "0.0.0+source"
