"""The options of a merge (``hdrmerge-cli merge``, :func:`hdrmerge_cli.merge`)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from hdrmerge_cli.core.noise import DEFAULT_K

#: extra EXR channels a user may ask for
EXTRA_CHANNELS = ("clipped", "weight", "ghost", "variance")

#: estimator choices: log = the paper's (7), ml = linear inverse-variance (censored)
ESTIMATORS = ("auto", "log", "ml")


@dataclass
class MergeOptions:
    """What to merge how, and where to write it.  Strings are as the command line takes
    them (``--weights``, ``--crf`` ...); ``output`` may be None for a merge kept in
    memory (:func:`hdrmerge_cli.merge`)."""

    output: Path | None = None
    profile_out: Path | None = None
    overwrite: bool = False
    weights: str = "auto"
    crf: str | None = None
    times: list[float] | str | None = None
    times_file: str | None = None
    reference: str = "geomean"
    cfa: bool = False
    half: bool = False
    extra_channels: tuple[str, ...] = field(default_factory=tuple)
    noise: str | None = None
    profile: str | None = None
    variance: str = "auto"
    estimator: str = "auto"
    irls: int | None = None  # None: models.default_irls
    k: float = DEFAULT_K
    lut: str | None = None
    bounds: str | None = None
    preview: Path | None = None
    preview_size: int = 2048
    align: str = "auto"
    deghost: str = "off"
    #: read/store bracket noise measurements in the per-camera cache (``--no-cache``: off)
    noise_cache: bool = True
    #: output colour space (a key of :data:`hdrmerge_cli.core.output_colorspace.COLORSPACES`)
    colorspace: str = "rec709"
    #: OpenEXR compression (a key of :data:`hdrmerge_cli.io.images.EXR_COMPRESSIONS`)
    compression: str = "auto"
