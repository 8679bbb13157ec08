"""The Python API: HDR merging of exposure stacks held as NumPy arrays, and of files.

Arrays in, arrays out, as in scikit-image or colour-hdri.  ``stack`` is the frames of one
bracket, any order: a sequence of K arrays of one shape and dtype, or one array whose
first axis is the frame.  Each frame is

* an image, ``(H, W, 3)`` or ``(H, W)`` uint8/uint16 code values through the camera
  response ``response`` (a JPEG's or TIFF's pixels), or
* with ``cfa="RGGB"`` (``"BGGR"``, ``"GRBG"``, ``"GBRG"``), an ``(H, W)`` uint16 Bayer
  mosaic of linear sensor data (black level ``black``, clipping at ``white``).

``times`` are the frames' exposure times in seconds (any unit proportional to the light
collected will do).  Radiance comes out in units of the full-scale signal per second: a
frame of ``t`` seconds records the linear signal ``radiance * t`` (1 = clipping) unless
``reference`` says otherwise.

* :func:`merge`: the merged radiance (and its variance), the estimate (7) of Goossens et
  al. 2012 under their noise model (17);
* :func:`estimate_response`: the camera response, measured on the stack;
* :func:`estimate_noise`: the parameters of (17) per channel, measured on the stack;
* :func:`register`: the warps that bring the frames onto the reference frame;
* :func:`ghost_mask`: per frame, where it is dropped as inconsistent with the reference.

Each runs the stage of ``hdrmerge-cli merge`` of that name on the arrays (caches off), so
it returns what the command would use.  :func:`merge_files` merges files as the command
does, returning a :class:`Merged` that writes the EXR.

>>> import numpy as np, hdrmerge_cli
>>> rng = np.random.default_rng(0)
>>> scene = np.geomspace(0.02, 60.0, 48 * 64).reshape(48, 64, 1) * [1.0, 0.8, 0.6]  # full scale per s
>>> times = [1 / 64, 1 / 8, 1.0]
>>> stack = [np.clip(rng.poisson(scene * t * 20000) / 20000 * 65535, 0, 65535).astype(np.uint16) for t in times]
>>> hdr = hdrmerge_cli.merge(stack, times, response="linear", align="off")
>>> hdr.shape, hdr.dtype
((48, 64, 3), dtype('float32'))
>>> float(np.median(np.abs(hdr / scene - 1))) < 0.02                  # photon noise: 20000 e- full scale
True
"""
from __future__ import annotations

import logging
import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hdrmerge_cli.core.crf import CRF, gamma_crf, table_crf
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import DEFAULT_K, NoiseParams
from hdrmerge_cli.io.frames import Frame, HeldCodes
from hdrmerge_cli.pipeline.options import ESTIMATORS, MergeOptions, MergeSettings, OutputOptions
from hdrmerge_cli.pipeline.output import Merged

__all__ = ["CRF", "Merged", "MergeSettings", "NoiseParams", "Registration", "estimate_noise", "estimate_response",
           "ghost_mask", "merge", "merge_files", "register"]

log = logging.getLogger("hdrmerge_cli")

#: LibRaw's colour index (R 0, G 1, B 2, second green 3) of each Bayer pattern's 2 x 2 cell
_CFA_INDEX = {"RGGB": [[0, 1], [3, 2]], "BGGR": [[2, 3], [1, 0]], "GRBG": [[1, 0], [2, 3]], "GBRG": [[3, 2], [0, 1]]}

_DOC_STACK = """stack : sequence of K arrays, or an array of shape (K, ...)
        The frames, any order: ``(H, W, 3)`` or ``(H, W)`` uint8/uint16 images, or with
        ``cfa`` ``(H, W)`` uint16 Bayer mosaics.
    times : sequence of K float
        Exposure times in seconds, positive."""


# ---------------------------------------------------------------- the stack
@dataclass
class _Stack:
    """A stack as the pipeline reads a bracket: frames sorted by exposure (``frames[k]``
    is input frame ``order[k]``), ``load(frame)`` their codes (held by frame)."""

    frames: list[Frame]
    load: HeldCodes
    order: np.ndarray
    grey: bool

    @property
    def raw(self) -> bool:
        return self.frames[0].kind == "raw"

    @property
    def exposures(self) -> np.ndarray:
        from hdrmerge_cli.io.metadata import exposure_values

        return exposure_values(self.frames)

    def to_input_order(self, per_frame: list) -> list:
        out = [None] * len(per_frame)
        for k, item in enumerate(per_frame):
            out[int(self.order[k])] = item
        return out


def _stack(stack, times, cfa: str | None = None, black: float = 0.0, white: float | None = None,
           bits: int | None = None) -> _Stack:
    """Check ``stack`` and ``times`` and describe the frames as the pipeline's
    :class:`~hdrmerge_cli.io.frames.Frame` (sorted by exposure)."""
    if isinstance(stack, (str, Path)) or (isinstance(stack, Sequence) and stack
                                          and isinstance(stack[0], (str, Path))):
        raise HdrMergeError("the stack holds file names: merge arrays with hdrmerge_cli.merge, files with "
                            "hdrmerge_cli.merge_files")
    arrays = [np.asarray(c) for c in stack]
    try:
        times = [float(t) for t in np.atleast_1d(np.asarray(times, dtype=object))]
    except (TypeError, ValueError):
        raise HdrMergeError("times: exposure times are numbers of seconds") from None
    if not arrays:
        raise HdrMergeError("no input frames given")
    if len(times) != len(arrays):
        raise HdrMergeError(f"{len(arrays)} frames but {len(times)} exposure times")
    first = arrays[0]
    for k, a in enumerate(arrays):
        if a.shape != first.shape or a.dtype != first.dtype:
            raise HdrMergeError(f"frame {k}: {a.dtype} {a.shape} differs from frame 0's {first.dtype} {first.shape}")
        if not np.isfinite(times[k]) or times[k] <= 0:
            raise HdrMergeError(f"frame {k}: exposure time {times[k]!r} is not a positive number")
    if first.dtype not in (np.uint8, np.uint16):
        raise HdrMergeError(f"codes must be uint8 or uint16, not {first.dtype}")
    container = 8 * first.dtype.itemsize
    bits = bits or container
    if not 1 <= bits <= container:
        raise HdrMergeError(f"bits: {bits} significant bits do not fit {first.dtype} codes")
    white = float(white if white is not None else (2**bits - 1))
    if not (math.isfinite(black) and math.isfinite(white) and black < white):
        raise HdrMergeError(f"white level {white:g} is not above the black level {black:g}")
    order = np.argsort(times, kind="stable")
    frames = [_frame(f"<array {order[k]}>", arrays[i], times[i], cfa, black, white, bits, container)
              for k, i in enumerate(order)]
    grey = frames[0].kind == "image" and first.ndim == 2  # decoded images are (H, W, C)
    held = HeldCodes()
    for f, i in zip(frames, order):
        held.hold(f, arrays[i][..., None] if grey else arrays[i])
    return _Stack(frames, held, order, grey)


def _frame(name: str, a: np.ndarray, t: float, cfa_pattern: str | None, black: float, white: float, bits: int,
           container: int) -> Frame:
    h, w = a.shape[:2]
    common = dict(path=name, width=w, height=h, exposure_time=t, iso=None, aperture=None, make="", model="",
                  timestamp=None, bits=bits, n_codes=2**container)
    if cfa_pattern is not None:
        if cfa_pattern not in _CFA_INDEX:
            raise HdrMergeError(f"unsupported colour filter pattern {cfa_pattern!r} "
                                f"(choose from {', '.join(_CFA_INDEX)})")
        if a.ndim != 2 or h % 2 or w % 2:
            raise HdrMergeError(f"a Bayer mosaic is an (H, W) array of even sides, not {a.shape}")
        return Frame(**common, kind="raw", black=np.full(4, black), white=np.full(4, white), channels=4,
                     cfa_pattern=cfa_pattern, channel_colors="RGBG",
                     cfa_cell=np.array(_CFA_INDEX[cfa_pattern], np.intp))
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (1, 3)):
        raise HdrMergeError(f"an image is (H, W) or (H, W, 3), not {a.shape} (give cfa for a mosaic)")
    channels = 1 if a.ndim == 2 else a.shape[2]
    return Frame(**common, kind="image", black=np.full(channels, black), white=np.full(channels, white),
                 channels=channels, channel_colors="RGB" if channels == 3 else "Y")


# ---------------------------------------------------------------- models given as objects
def _given_response(response, st: _Stack) -> CRF:
    """The response a caller gave (a CRF, ``"linear"``, ``"srgb"``, a gamma as a number, an
    inverse table), or for None sRGB marked assumed (the merge then measures it)."""
    if st.raw:
        if response is not None and not (isinstance(response, str) and response == "linear") and not (
                isinstance(response, CRF) and response.is_linear):
            raise HdrMergeError("a Bayer mosaic is linear sensor data: leave response unset")
        return CRF("linear")
    if response is None:
        return CRF("srgb", assumed=True)
    if isinstance(response, CRF):
        crf = response
    elif isinstance(response, str):
        if response not in ("linear", "srgb"):
            raise HdrMergeError(f"response {response[:40]!r}: give 'linear', 'srgb', a gamma (a number), an inverse "
                                "table or a CRF")
        crf = CRF(response)
    elif isinstance(response, numbers.Real):
        crf = gamma_crf(float(response), "response")
    elif isinstance(response, (np.ndarray, Sequence)):
        crf = table_crf(np.asarray(response, np.float64), "table")
    else:
        raise HdrMergeError(f"response: a CRF, 'linear', 'srgb', a gamma or an inverse table, not "
                            f"{type(response).__name__}")
    n = st.frames[0].n_codes
    if crf.table is not None and crf.table.shape[1] != n:
        raise HdrMergeError(f"response: the inverse table has {crf.table.shape[1]} entries per channel, but the codes "
                            f"take {n} values")
    return crf


def _response(response, st: _Stack) -> CRF:
    """:func:`_given_response`, with None measured on the stack as the merge measures it
    (sRGB, with a warning, where the stack cannot pin it)."""
    crf = _given_response(response, st)
    if not crf.assumed:
        return crf
    from hdrmerge_cli.pipeline.response import measure_response
    from hdrmerge_cli.pipeline.exposure_check import ordered_samples

    h = st.exposures
    return measure_response(st.frames, h, ordered_samples(st.frames, h, st.load), cache=False) or crf


def _noise(noise) -> dict[str, NoiseParams] | None:
    """Noise parameters as the pipeline takes them, ``{channel or "*": NoiseParams}``."""
    if noise is None:
        return None
    try:
        if isinstance(noise, NoiseParams):
            return {"*": noise}
        if isinstance(noise, Mapping):
            if {"sigma_o2", "alpha"} <= set(noise):
                return {"*": NoiseParams(**noise)}
            out = {}
            for ch, p in noise.items():
                out[str(ch).upper()] = p if isinstance(p, NoiseParams) else NoiseParams(**p)
            if out:
                return out
    except (TypeError, ValueError) as exc:
        raise HdrMergeError(f"noise: {exc}") from None
    raise HdrMergeError("noise: a NoiseParams, a dict of sigma_o2, alpha (and beta), or such per channel "
                        "({'R': ..., 'G': ..., 'B': ...})")


def _choice(name: str, value, choices) -> None:
    if not isinstance(value, str) or value not in choices:
        raise HdrMergeError(f"{name}: {value!r} is not one of {', '.join(choices)}")


def _settings(weighting, estimator, variance_model, irls, k, align, deghost, reference) -> MergeSettings:
    """The checked :class:`MergeSettings` of the array API's keywords."""
    from hdrmerge_cli.core.choices import VARIANCE_FACTORS
    from hdrmerge_cli.core.weights import WEIGHTING_FUNCTIONS
    from hdrmerge_cli.io.metadata import reference_exposure
    from hdrmerge_cli.pipeline.options import ALIGN_MODES, DEGHOST_MODES

    _choice("weighting", weighting, ("auto", *sorted(WEIGHTING_FUNCTIONS)))
    _choice("estimator", estimator, ESTIMATORS)
    _choice("variance_model", variance_model, ("auto", *VARIANCE_FACTORS))
    _choice("align", align, ALIGN_MODES)
    _choice("deghost", deghost, DEGHOST_MODES)
    if irls is not None and (not isinstance(irls, numbers.Integral) or not 0 <= irls <= 50):
        raise HdrMergeError(f"irls: {irls!r} is not a number of passes from 0 to 50")
    if not isinstance(k, numbers.Real) or not 0.5 <= k <= 10:
        raise HdrMergeError(f"k: {k!r} is not a number of standard deviations from 0.5 to 10")
    reference_exposure(reference, np.ones(1))
    return MergeSettings(estimator=estimator, weights=weighting, variance=variance_model, irls=irls, k=float(k),
                         align=align, deghost=deghost, reference=reference)


def _merge_stack(stack, times, settings: MergeSettings, response, noise, cfa, black, white, bits, demosaic: bool,
                 return_variance: bool):
    """:func:`merge` once its settings are checked: the radiance, float32 ``(H, W, 3)`` or
    ``(H, W)``, and with ``return_variance`` the pair (radiance, variance)."""
    from hdrmerge_cli.pipeline.records import Bracket
    from hdrmerge_cli.pipeline.run import check_options, merge_frames

    st = _stack(stack, times, cfa, black, white, bits)
    crf = _given_response(response, st)
    params = _noise(noise)
    opts = MergeOptions(settings, io=OutputOptions(extra_channels=("variance",) if return_variance else (),
                                                   cfa=st.raw and not demosaic, noise_cache=False))
    check_options(opts)
    merged = merge_frames(Bracket(st.frames, crf, st.load, noise=params), opts)
    image = merged.image
    variance = merged.variance if return_variance else None
    if image.shape[-1] == 1:  # a grey image, or a mosaic not demosaiced
        image = image[..., 0]
        variance = variance[..., 0] if variance is not None else None
    return (image, variance) if return_variance else image


# ---------------------------------------------------------------- the functions
def merge(stack, times, *, response=None, noise=None, weighting: str = "auto", estimator: str = "auto",
          variance_model: str = "auto", irls: int | None = None, k: float = DEFAULT_K, align: str = "auto",
          deghost: str = "off", reference: float | str = 1.0, cfa: str | None = None, black: float = 0.0,
          white: float | None = None, bits: int | None = None, demosaic: bool = True, return_variance: bool = False):
    """Merge an exposure stack into one scene-linear radiance image.

    Parameters
    ----------
    {stack}
    response : CRF, str, float, array or None
        The images' camera response: a :class:`~hdrmerge_cli.core.crf.CRF` (e.g. from
        :func:`estimate_response`), ``"linear"``, ``"srgb"``, a gamma ``G`` (``v = x**(1/G)``), or
        a ``(N,)`` or ``(C, N)`` table of the inverse response, the linear signal per code value.
        None: measured (:func:`estimate_response`; sRGB, warned, where the stack cannot pin it).
    noise : NoiseParams, dict or None
        The noise model (17) in code units of the linear signal, as a dict ``{{"sigma_o2",
        "alpha", "beta"}}`` or a :class:`~hdrmerge_cli.core.noise.NoiseParams`, or either per
        channel (``{{"R": ..., "G": ..., "B": ...}}``; mosaics also ``"G2"``).  None: measured
        where the merge needs it (:func:`estimate_noise`: mosaics and linear images always).
    weighting : str
        The weighting function of (7): ``"auto"`` (uniform for ML, triangle for log),
        ``"triangle"``, ``"uniform"``, ``"probabilistic"`` (32), ``"direct"`` (33),
        ``"optimal"`` (29), ``"bounded"``, ``"mann"``, ``"deneve"``, ``"gaussian"``.
    estimator : {{"auto", "log", "ml"}}
        ``log``: the paper's log-domain (7); ``ml``: linear inverse-variance, clipped readings
        censored.  auto: ml for mosaics, linear images and images whose exposure pairs the noise
        model explains (a 1e-3 false-alarm test), log for the rest (camera processing).
    variance_model : {{"auto", "model", "codes", "photon", "none"}}
        The variance factor of (7); auto: model for the ML estimator and for mosaics and
        linear images when noise parameters are known, codes for the log estimator of images.
    irls : int, optional
        Re-weighting passes at the merged estimate (default: one for ML with a noise model).
    k : float
        Clipping margin of (47) in standard deviations.
    align : {{"auto", "off", "translation", "similarity"}}
        Registration onto the middle exposure (:func:`register`); auto applies it only when
        a frame is off by more than a quarter pixel.
    deghost : {{"off", "auto", "on"}}
        Drop moving objects (:func:`ghost_mask`).
    reference : float or str
        The exposure (seconds) whose full-scale signal is 1.0 in the result, or ``"geomean"``,
        ``"shortest"``, ``"longest"``; the default, 1 s, gives radiance in full scale per second.
    cfa : str, optional
        The mosaics' 2 x 2 colour filter pattern (their data is linear: no ``response``).
    black, white : float
        Code values of no light and of clipping (default 0 and ``2**bits - 1``, ``bits``
        the codes' significant bits, by default the dtype's).
    demosaic : bool
        Mosaics: False returns the merged ``(H, W)`` mosaic (camera-native: no white balance).
    return_variance : bool
        Also return the variance of each value under the noise model.

    Returns
    -------
    radiance : ndarray, float32, (H, W, 3)
        Scene-linear radiance in units of the full-scale signal of a ``reference`` s
        exposure; (H, W) for (H, W) images and mosaics not demosaiced (else white balance 1,
        the identity camera matrix).  Pixels clipped (dark) in every frame: a lower (upper) bound.
    variance : ndarray, float32, like ``radiance``
        Only with ``return_variance``: the variance of each value (units squared).

    Raises
    ------
    HdrMergeError
        Inconsistent frames or times, unknown option values (a one-line message).

    Examples
    --------
    >>> import numpy as np, hdrmerge_cli
    >>> scene = np.geomspace(0.01, 20.0, 60 * 80).reshape(60, 80)          # a ramp, full scale per s
    >>> times = [1 / 16, 1 / 4, 1.0]
    >>> stack = [np.round(255 * np.clip(scene * t, 0, 1) ** (1 / 2.2)).astype(np.uint8) for t in times]
    >>> hdr, var = hdrmerge_cli.merge(stack, times, response=2.2, return_variance=True)
    >>> hdr.shape, var.shape
    ((60, 80), (60, 80))
    >>> bool(np.all(np.abs(hdr / scene - 1)[(scene > 0.02) & (scene < 15)] < 0.05))
    True
    """
    settings = _settings(weighting, estimator, variance_model, irls, k, align, deghost, reference)
    return _merge_stack(stack, times, settings, response, noise, cfa, black, white, bits, demosaic, return_variance)


def estimate_response(stack, times, *, black: float = 0.0, white: float | None = None,
                      bits: int | None = None) -> CRF:
    """Measure the camera response of an image stack (the merge's measured response:
    ``estimate-crf``'s Goossens fit with its prior towards sRGB where the frames leave the
    curve open, the exposure labels checked through it).

    Parameters
    ----------
    {stack}
        Images only: a mosaic is linear.  Two distinct exposures at least, neighbours
        sharing unclipped pixels.
    black, white, bits :
        As for :func:`merge`.

    Returns
    -------
    CRF
        ``.table``: ``(C, N)`` float64, the inverse response (linear signal in [0, 1]) at
        each of the ``N`` code values per channel; ``.inverse(v, c)`` and ``.forward(x, c)``
        map normalised codes ``v = z / (N - 1)`` to linear ``x`` and back.  Pass it as
        :func:`merge`'s ``response``.

    Raises
    ------
    HdrMergeError
        A mosaic; frames whose order contradicts their times; a stack that cannot pin a
        response (one exposure, too little overlap, a flat fit).

    Examples
    --------
    >>> import numpy as np, hdrmerge_cli
    >>> scene = np.geomspace(0.01, 20.0, 96 * 128).reshape(96, 128)
    >>> times = [1 / 16, 1 / 4, 1.0]
    >>> stack = [np.round(255 * np.clip(scene * t, 0, 1) ** (1 / 2.2)).astype(np.uint8) for t in times]
    >>> crf = hdrmerge_cli.estimate_response(stack, times)
    >>> crf.table.shape
    (1, 256)
    >>> round(float(crf.inverse(128 / 255)), 2)   # gamma 2.2: (128/255)**2.2 = 0.22
    0.22
    """
    from hdrmerge_cli.core.crf_estimate import labelled_fit, thin_overlap
    from hdrmerge_cli.pipeline.response import is_flat, log_labelled_fit
    from hdrmerge_cli.pipeline.exposure_check import ordered_samples

    st = _stack(stack, times, None, black, white, bits)
    if len(np.unique(st.exposures)) < 2:
        raise HdrMergeError("a response is measured on two exposures or more")
    samples = ordered_samples(st.frames, st.exposures, st.load)
    thin = thin_overlap(samples)
    if thin is not None:
        k, both = thin
        raise HdrMergeError(f"frames {st.order[k - 1]} and {st.order[k]} share {both} unclipped pixels: too few to "
                            "chain a response across")
    fit = labelled_fit(samples, st.exposures)
    log_labelled_fit(st.frames, fit, False)
    crf = fit.crf
    if is_flat(crf):
        raise HdrMergeError("the response fitted on the stack is flat: the frames do not pin it")
    return CRF("measured", table=crf.table)


def estimate_noise(stack, times, *, response=None, cfa: str | None = None, black: float = 0.0,
                   white: float | None = None, bits: int | None = None) -> dict[str, NoiseParams]:
    """Measure the noise model (17) of the camera on the stack, per channel, as the merge
    does when given none (``calibrate-noise``'s fit on a subsample of each frame: local
    means and variances, read noise and gain; the gain FPN ``beta`` is left 0, as scene
    texture cannot be told from it on photographs).

    Parameters
    ----------
    {stack}
    response : CRF, str, float, array or None
        As for :func:`merge`: images are measured on their signal linearised through it.
    cfa, black, white, bits :
        As for :func:`merge`.

    Returns
    -------
    dict of str to NoiseParams
        Per channel name (``"R"``, ``"G"``, ``"B"``, mosaics also ``"G2"``; grey ``"Y"``):
        ``sigma_o2`` (read noise, code values squared), ``alpha`` (gain, code values squared
        per electron), ``beta`` (0).  Code values are those of the linear signal above black
        (images: the linearised codes, full scale ``white``).  Pass it as :func:`merge`'s
        ``noise``.

    Raises
    ------
    HdrMergeError
        No frame with usable texture-free regions (all clipped or black), bad input.

    Examples
    --------
    12-bit mosaics of grey patches: 0.5 code values per electron (``alpha`` = 0.25), read
    noise of 3 code values (``sigma_o2`` = 9), black at 64:

    >>> import numpy as np, hdrmerge_cli
    >>> rng = np.random.default_rng(1)
    >>> scene = np.kron(np.geomspace(20, 3500, 32).reshape(4, 8), np.ones((24, 16)))  # code values per s
    >>> times = [0.25, 1.0]
    >>> stack = [np.clip(np.round(0.5 * rng.poisson(scene * t / 0.5) + rng.normal(0, 3, scene.shape) + 64),
    ...                  0, 4095).astype(np.uint16) for t in times]
    >>> noise = hdrmerge_cli.estimate_noise(stack, times, cfa="RGGB", black=64, white=4095, bits=12)
    >>> sorted(noise)
    ['B', 'G', 'G2', 'R']
    >>> p = noise["R"]
    >>> bool(0.2 < p.alpha < 0.3 and 6 < p.sigma_o2 < 13), p.beta
    (True, 0.0)
    """
    from hdrmerge_cli.io.metadata import sample_pattern
    from hdrmerge_cli.pipeline.noise import estimate_bracket_noise

    st = _stack(stack, times, cfa, black, white, bits)
    crf = _response(response, st)
    used, _, _ = estimate_bracket_noise(st.frames, crf, st.load, sample_pattern(st.frames[0]))
    return {ch.upper(): NoiseParams(**p) for ch, p in used.items()}


@dataclass(frozen=True)
class Registration:
    """What :func:`register` found.

    Attributes
    ----------
    warps : ndarray, float64, (K, 2, 3)
        Per input frame, the affine map from the reference frame's pixel coordinates
        ``(x, y, 1)`` (x along a row) to that frame's: frame ``k`` resampled at
        ``warps[k] @ (x, y, 1)`` lies on the reference.  The identity for the reference
        and for frames that could not be registered.
    applied : bool
        Whether the merge applies them (``motion="auto"``: some frame is off by more than
        a quarter pixel).
    reference : int
        The input index of the reference frame (the middle exposure).
    confidence : ndarray, float64, (K,)
        Each registration's correlation coefficient to its neighbour (1 for the reference).
    """

    warps: np.ndarray
    applied: bool
    reference: int
    confidence: np.ndarray


def register(stack, times, *, response=None, motion: str = "auto", cfa: str | None = None, black: float = 0.0,
             white: float | None = None, bits: int | None = None) -> Registration:
    """Register the frames of a hand-held stack onto its middle exposure, as the merge does
    (phase correlation and ECC on exposure-normalised log irradiance, each frame to its
    neighbour towards the reference, chained; checked tile by tile).

    Parameters
    ----------
    {stack}
    response : CRF, str, float, array or None
        As for :func:`merge` (the frames are compared as linear signal).
    motion : {{"auto", "translation", "similarity"}}
        The motion model; auto keeps a rotation only where it beats translation.
    cfa, black, white, bits :
        As for :func:`merge`.  Mosaics register on 2 x 2 cells; their warps are in mosaic
        pixels.

    Returns
    -------
    Registration
        ``.warps`` (K, 2, 3) float64, ``.applied``, ``.reference``, ``.confidence``.

    Examples
    --------
    The longer frame (the reference, the middle exposure of two) sees the scene 3 px further
    right and 2 px further down, so the shorter one is read 3 px left and 2 px up:

    >>> import numpy as np, hdrmerge_cli
    >>> rng = np.random.default_rng(2)
    >>> scene = np.exp(rng.standard_normal((140, 180)))
    >>> import cv2; scene = cv2.GaussianBlur(scene, (0, 0), 2) * 0.2          # texture, full scale per s
    >>> times = [0.5, 2.0]
    >>> moved = np.roll(scene, (2, 3), axis=(0, 1))
    >>> stack = [np.round(255 * np.clip(s * t, 0, 1) ** (1 / 2.2)).astype(np.uint8)
    ...          for s, t in zip((scene, moved), times)]
    >>> reg = hdrmerge_cli.register(stack, times, response=2.2, motion="translation")
    >>> reg.reference, np.round(reg.warps[0][:, 2]).tolist(), reg.warps[1].tolist() == [[1, 0, 0], [0, 1, 0]]
    (1, [-3.0, -2.0], True)
    """
    from hdrmerge_cli.io.metadata import reference_index
    from hdrmerge_cli.pipeline.run import align

    if motion == "off":
        raise HdrMergeError("motion: 'off' registers nothing; choose auto, translation or similarity")
    _choice("motion", motion, ("auto", "translation", "similarity"))
    st = _stack(stack, times, cfa, black, white, bits)
    crf = _response(response, st)
    alignment = align(st.frames, st.exposures, crf, motion, st.load)
    warps = np.array(st.to_input_order([np.asarray(w, np.float64) for w in alignment.warps]))
    confidence = np.array(st.to_input_order(list(alignment.confidence)), np.float64)
    return Registration(warps, alignment.applied, int(st.order[reference_index(st.frames)]), confidence)


def ghost_mask(stack, times, *, response=None, noise=None, mode: str = "on", align: str = "off",
               cfa: str | None = None, black: float = 0.0, white: float | None = None,
               bits: int | None = None) -> np.ndarray:
    """Where each frame disagrees with the reference (the middle exposure) beyond its noise:
    the merge's deghosting masks, per pixel.

    Each frame is tested block by block against the reference under the noise model (a
    chi-square test at a false-alarm rate of 1e-3, with the bounds a dark or clipped
    reading sets), the rejected regions cleaned and feathered.

    Parameters
    ----------
    {stack}
    response : CRF, str, float, array or None
        As for :func:`merge`.
    noise : NoiseParams, dict or None
        As for :func:`merge`.  None: measured for mosaics; for images the codes'
        quantisation, the rest measured on the frames.
    mode : {{"on", "auto"}}
        ``auto``: all zero unless some frame has more than 0.2 % of its blocks rejected.
    align : {{"off", "auto", "translation", "similarity"}}
        Register first (:func:`register`); the masks are then on the reference's pixels.
    cfa, black, white, bits :
        As for :func:`merge`.

    Returns
    -------
    ndarray, float32, (K, H, W)
        Per input frame and pixel, how much of the frame is dropped: 0 kept, 1 dropped
        (soft at region edges).  The reference is never dropped.

    Examples
    --------
    A bright rectangle in the longest frame only:

    >>> import numpy as np, hdrmerge_cli, cv2
    >>> rng = np.random.default_rng(3)
    >>> scene = 0.3 * np.exp(cv2.GaussianBlur(rng.standard_normal((96, 128)), (0, 0), 3))  # full scale per s
    >>> times = [0.25, 0.5, 1.0]
    >>> frames = [scene * t for t in times]
    >>> frames[2] = frames[2].copy(); frames[2][30:60, 40:80] *= 2.5
    >>> stack = [np.clip(np.round(4000 * f + rng.normal(0, 2, f.shape)), 0, 4095).astype(np.uint16)
    ...          for f in frames]
    >>> masks = hdrmerge_cli.ghost_mask(stack, times, response="linear", bits=12)
    >>> masks.shape, float(masks[2, 45, 60]), float(masks[2, 5, 5]), float(masks[0].max())
    ((3, 96, 128), 1.0, 0.0, 0.0)
    """
    from hdrmerge_cli.io.metadata import sample_pattern
    from hdrmerge_cli.pipeline.choices import choose_deghost
    from hdrmerge_cli.pipeline.ghosts import find_ghosts
    from hdrmerge_cli.pipeline.options import ALIGN_MODES
    from hdrmerge_cli.pipeline.register import loader
    from hdrmerge_cli.pipeline.run import align as align_frames

    _choice("mode", mode, ("on", "auto"))
    _choice("align", align, ALIGN_MODES)
    st = _stack(stack, times, cfa, black, white, bits)
    crf = _response(response, st)
    params = _noise(noise)
    if params is None and st.raw:  # as the merge: a mosaic's noise is measured
        from hdrmerge_cli.pipeline.noise import measure_noise

        params, _ = measure_noise(st.frames, crf, st.load, sample_pattern(st.frames[0]), cache=False)
    alignment = align_frames(st.frames, st.exposures, crf, align, st.load) if align != "off" else None
    load = loader(alignment, st.load)
    ghosts = choose_deghost(find_ghosts(st.frames, st.exposures, sample_pattern(st.frames[0]), crf, params, load), mode)
    ghosts.report()
    h, w = st.frames[0].height, st.frames[0].width
    masks = np.zeros((len(st.frames), h, w), np.float32)
    if ghosts.applied:
        for k, frame in enumerate(st.frames):
            masks[st.order[k]] = ghosts.weight(frame, h, w)
    return masks


for _f in (merge, estimate_response, estimate_noise, register, ghost_mask):
    _f.__doc__ = _f.__doc__.replace("{stack}", _DOC_STACK).replace("{{", "{").replace("}}", "}")
del _f


# ---------------------------------------------------------------- files
def merge_files(paths: Sequence[str | Path], **options) -> Merged:
    """Merge the bracket of image or RAW files ``paths`` (any order), as ``hdrmerge-cli
    merge`` does.

    Parameters
    ----------
    paths : sequence of str or Path
        The frames: RAW files (LibRaw), or 8/16-bit JPEG/TIFF/PNG; exposure times from EXIF
        unless ``times`` is given.
    **options
        The fields of :class:`~hdrmerge_cli.pipeline.options.MergeOptions` as the command
        line takes them: :class:`MergeSettings` (``align="auto"``, ``deghost="on"``,
        ``reference=0.01`` ...), the inputs' text (``crf="gamma:2.2"``,
        ``noise="sigma_o2=4,alpha=1"``, ``profile``, ``times``, ``times_file``) and the
        outputs' (``extra_channels=("variance",)``, ``colorspace="acescg"``, ``cfa``,
        ``noise_cache`` ...); ``output`` is not needed (:meth:`Merged.write` takes it).
        ``crf`` may also be a :class:`CRF` (e.g. from :func:`estimate_response`) and
        ``noise`` what :func:`merge` takes (e.g. from :func:`estimate_noise`).

    Returns
    -------
    Merged
        ``.image`` (H, W, 3) float32 scene-linear (1.0 = the full-scale signal of an
        exposure of ``.h_ref`` seconds), ``.flags`` (H, W) int8 (1 saturated, -1 dark),
        ``.variance`` (with ``extra_channels=("variance",)``), ``.profile()``, ``.summary()``
        and ``.write(path)`` (EXR, or a float DNG from RAW).

    Raises
    ------
    HdrMergeError
        Unreadable or inconsistent frames, bad options (one-line message).

    Examples
    --------
    >>> merged = merge_files(["a.CR2", "b.CR2", "c.CR2"], align="auto")   # doctest: +SKIP
    >>> merged.image.shape, merged.flags.shape                              # doctest: +SKIP
    ((3456, 5184, 3), (3456, 5184))
    >>> merged.write("out.exr")                                             # doctest: +SKIP
    """
    from hdrmerge_cli.pipeline.run import merge_bracket

    noise = options.pop("noise") if not isinstance(options.get("noise"), (str, type(None))) else None
    crf = options.pop("crf") if isinstance(options.get("crf"), CRF) else None
    opts = _options(options)
    return merge_bracket([str(p) for p in paths], opts, noise=_noise(noise), crf=crf)


def merge_arrays(codes: Sequence[np.ndarray], exposure_times: Sequence[float], *, crf: str | CRF = "srgb",
                 cfa_pattern: str | None = None, black: float = 0.0, white: float | None = None,
                 bits: int | None = None, **options) -> Merged:
    """Decoded frames merged with :func:`merge_files`'s options (the response as the command
    line's text or a :class:`CRF`), returning the whole :class:`Merged`: its summary and
    every stage's result (``.bracket.alignment``, ``.bracket.ghosts``, ``.bracket.models``;
    ``.reconstruction``), for tests and benchmarks that inspect a merge's stages.
    ``codes``, ``cfa_pattern``, ``black``, ``white``, ``bits`` as :func:`merge`'s ``stack``,
    ``cfa``, ``black``, ``white``, ``bits``."""
    st = _stack(codes, exposure_times, cfa_pattern, black, white, bits)
    options.setdefault("noise_cache", False)  # no camera to key a cache entry by
    opts = _options(options)
    from hdrmerge_cli.pipeline.bracket import choose_crf
    from hdrmerge_cli.pipeline.records import Bracket
    from hdrmerge_cli.pipeline.run import given_noise, merge_frames

    # a mosaic is linear whatever is given; an image's text as --crf's (none: merge_frames measures it)
    response = crf if isinstance(crf, CRF) and not st.raw else choose_crf(st.frames, None if st.raw else crf,
                                                                            warn=False)
    return merge_frames(given_noise(Bracket(st.frames, response, st.load), opts.inputs), opts)


def _options(options: dict) -> MergeOptions:
    """The checked :class:`MergeOptions` of :func:`merge_files`'s keywords.  Times may be
    numbers (seconds) or text as on the command line: ``reference=0.01`` or ``"1/100"``,
    ``times=[0.01, 0.04]``, ``"1/100,1/25"`` or ``"estimate"``."""
    from hdrmerge_cli.io.times import ESTIMATE, parse_times, seconds
    from hdrmerge_cli.pipeline.run import check_options

    times = options.get("times")
    if isinstance(times, str):
        options["times"] = ESTIMATE if times.strip().lower() == ESTIMATE else parse_times(times)
    elif times is not None:
        try:
            options["times"] = [seconds(t) for t in times]
        except (HdrMergeError, TypeError) as exc:
            raise HdrMergeError(f"times: {exc}") from None
    try:
        opts = MergeOptions.from_fields(**options)
    except TypeError as exc:
        raise HdrMergeError(str(exc)) from None
    check_options(opts)
    return opts
