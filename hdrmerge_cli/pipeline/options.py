"""The options of a merge, in three parts that say what they are about.

* :class:`MergeSettings`: how to merge (the algorithm): estimator, weights, variance,
  re-weighting, registration, deghosting, the output's reference exposure.  The array API
  (:func:`hdrmerge_cli.merge`) takes these and nothing else.
* :class:`InputOptions`: what the files are, as the command line describes them (text
  resolved when the bracket is read: ``--crf gamma:2.2``, ``--noise sigma_o2=4,alpha=1``,
  a profile, exposure times).
* :class:`OutputOptions`: what is written where (EXR, profile, preview, their format)
  and the per-camera cache.

:class:`MergeOptions` composes the three for ``hdrmerge-cli merge`` and
:func:`hdrmerge_cli.merge_files`; each stage takes the part (or the fields) it reads.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from hdrmerge_cli.core.noise import DEFAULT_K

#: extra EXR channels a user may ask for
EXTRA_CHANNELS = ("clipped", "weight", "ghost", "variance")

#: estimator choices: log = the paper's (7), ml = linear inverse-variance (censored)
ESTIMATORS = ("auto", "log", "ml")

#: registration (:mod:`hdrmerge_cli.pipeline.register`) and deghosting (:mod:`hdrmerge_cli.pipeline.ghosts`) choices
ALIGN_MODES = ("off", "auto", "translation", "similarity")
DEGHOST_MODES = ("off", "auto", "on")

#: ``--batch``'s default largest time (s) from the end of one exposure to the start of the
#: next inside one bracket (HDRMerge's -g default; :mod:`hdrmerge_cli.pipeline.batch`)
DEFAULT_GAP = 3.0


@dataclass(frozen=True)
class MergeSettings:
    """How a bracket is merged; each ``auto`` is resolved per bracket
    (:mod:`hdrmerge_cli.pipeline.choices`).

    estimator : ``auto``, ``log`` (the paper's (7)) or ``ml`` (linear, censored)
    weights : ``auto`` or a key of :data:`hdrmerge_cli.core.weights.WEIGHTING_FUNCTIONS`
    variance : the variance factor of (7): ``auto``, ``model``, ``codes``, ``photon``, ``none``
    irls : re-weighting passes at the merged estimate (None: the estimator's default)
    k : clipping margin of (47), in standard deviations
    lut : a ``weights-lut`` table (CSV path) instead of ``weights``
    bounds : the bounded weights' upper bounds, as ``--bounds`` writes them
    align : registration: ``off``, ``auto``, ``translation``, ``similarity``
    deghost : ``off``, ``auto``, ``on``
    reference : the exposure (s) whose full-scale signal is 1.0 in the output:
        ``geomean``, ``shortest``, ``longest``, or seconds (number or text such as ``1/100``)
    """

    estimator: str = "auto"
    weights: str = "auto"
    variance: str = "auto"
    irls: int | None = None
    k: float = DEFAULT_K
    lut: str | None = None
    bounds: str | None = None
    align: str = "auto"
    deghost: str = "off"
    reference: str | float = "geomean"


@dataclass(frozen=True)
class InputOptions:
    """What the files of a bracket are, as text the command line takes; resolved when the
    bracket is read (:func:`hdrmerge_cli.pipeline.bracket.read`,
    :func:`hdrmerge_cli.pipeline.noise.resolve_noise`).

    crf : images' response: ``linear``, ``srgb``, ``gamma:G``, a CSV table or profile JSON
        (None: measured on the bracket)
    profile : a camera profile JSON (noise parameters and response)
    noise : ``sigma_o2=4,alpha=1,beta=0`` or per channel ``R:... G:...`` (None: measured)
    times : exposure times (s) in the order of the files, or ``"estimate"``
    times_file : lines ``name seconds``
    """

    crf: str | None = None
    profile: str | None = None
    noise: str | None = None
    times: list[float] | str | None = None
    times_file: str | None = None


@dataclass(frozen=True)
class OutputOptions:
    """What a merge writes, where and how.

    output : the EXR or float DNG (None: kept in memory, :meth:`Merged.write` takes a path)
    profile_out : the profile JSON (None: beside ``output``)
    overwrite : replace existing files
    cfa : RAW: write the merged mosaic (no demosaic, camera-native)
    half : 16-bit half floats
    extra_channels : a subset of :data:`EXTRA_CHANNELS` (``variance`` also makes the merge
        compute it)
    colorspace : a key of :data:`hdrmerge_cli.core.output_colorspace.COLORSPACES`
    compression : a key of :data:`hdrmerge_cli.io.images.EXR_COMPRESSIONS`
    preview, preview_size : a tone-mapped picture and its longest side (0: full size)
    noise_cache : read and store noise and response measurements in the per-camera cache
    crop : crop the EXR to the rectangle every aligned frame covers
    """

    output: Path | None = None
    profile_out: Path | None = None
    overwrite: bool = False
    cfa: bool = False
    half: bool = False
    extra_channels: tuple[str, ...] = field(default_factory=tuple)
    colorspace: str = "rec709"
    compression: str = "auto"
    preview: Path | None = None
    preview_size: int = 2048
    noise_cache: bool = True
    crop: bool = False


#: each flat field's part
_PARTS = {"algorithm": MergeSettings, "inputs": InputOptions, "io": OutputOptions}
_OWNER = {f.name: part for part, cls in _PARTS.items() for f in dataclasses.fields(cls)}


@dataclass(frozen=True)
class MergeOptions:
    """A file-level merge's options: ``algorithm`` (:class:`MergeSettings`), ``inputs``
    (:class:`InputOptions`) and ``io`` (:class:`OutputOptions`), each read by field
    (``opts.algorithm.deghost``); :meth:`from_fields` sorts the keywords of
    :func:`hdrmerge_cli.merge_files` into them.

    >>> opts = MergeOptions.from_fields(deghost="on", output=Path("m.exr"))
    >>> opts.algorithm.deghost, opts.io.output, opts.io.overwrite
    ('on', PosixPath('m.exr'), False)
    >>> opts.replace(overwrite=True).io.overwrite
    True
    """

    algorithm: MergeSettings = field(default_factory=MergeSettings)
    inputs: InputOptions = field(default_factory=InputOptions)
    io: OutputOptions = field(default_factory=OutputOptions)

    def __post_init__(self):
        for name, cls in _PARTS.items():
            if not isinstance(getattr(self, name), cls):
                raise TypeError(f"MergeOptions {name}: a {cls.__name__}, not {type(getattr(self, name)).__name__}")

    @classmethod
    def from_fields(cls, **fields) -> MergeOptions:
        """The options with each keyword in its part, the others at their defaults."""
        return cls().replace(**fields)

    def replace(self, **fields) -> MergeOptions:
        """A copy with the given fields (of any part, by name) changed."""
        unknown = sorted(set(fields) - set(_OWNER))
        if unknown:
            raise TypeError(f"MergeOptions: unknown option {unknown[0]!r}")
        parts = {name: getattr(self, name) for name in _PARTS}
        for name in parts:
            mine = {k: v for k, v in fields.items() if _OWNER[k] == name}
            if mine:
                parts[name] = dataclasses.replace(parts[name], **mine)
        return MergeOptions(**parts)
