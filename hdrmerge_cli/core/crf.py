"""Camera response functions (CRF) and their inverse tables.

The paper's (1) writes a code value as ``z = gamma(sqrt(alpha) t E)`` and (2) recovers
the log-irradiance through ``g(z) = log gamma^-1(z)``.  Here a CRF maps the *normalised*
linear sensor signal ``x in [0, 1]`` (1 = full scale, the clipping level ``y_max``) to the
normalised code value ``v = z / z_max in [0, 1]``; its inverse gives back ``x``.

Parametric CRFs are picked by name from :data:`CRF_MODELS`; measured CRFs are tables
``(C, N)`` of ``gamma^-1`` sampled at the ``N`` code values of each of ``C`` channels.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hdrmerge_cli.core.errors import HdrMergeError

#: the sRGB (IEC 61966-2-1) break point of the linear segment, in the linear domain
_SRGB_BREAK = 0.0031308


def _spow(a, p):
    """Sign-preserving power (as colour-science's ``spow``: negative values stay finite)."""
    return np.sign(a) * np.abs(a) ** p


def srgb_eotf(v) -> np.ndarray:
    """sRGB code value (normalised) -> linear (IEC 61966-2-1), float64; the same arithmetic
    as colour-science's ``eotf_sRGB`` without importing colour (~1-2 s with its plotting)."""
    v = np.asarray(v, dtype=np.float64)
    return np.where(_SRGB_BREAK * 12.92 >= v, v / 12.92, _spow((v + 0.055) / 1.055, 2.4))


def srgb_eotf_inverse(x) -> np.ndarray:
    """Linear -> sRGB code value (normalised), float64; as colour's ``eotf_inverse_sRGB``."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= _SRGB_BREAK, x * 12.92, 1.055 * _spow(x, 1 / 2.4) - 0.055)


#: accepted gamma of ``gamma:G``: beyond it the codes of an 8-bit image span more than
#: 80 stops (or less than one), which no camera records
GAMMA_RANGE = (0.1, 10.0)

#: name -> (forward gamma: x -> v, inverse gamma^-1: v -> x, takes a parameter)
CRF_MODELS = {
    "linear": (lambda x, p: np.asarray(x, np.float64), lambda v, p: np.asarray(v, np.float64), False),
    "srgb": (lambda x, p: srgb_eotf_inverse(x), lambda v, p: srgb_eotf(v), False),
    "gamma": (
        lambda x, p: np.power(np.clip(x, 0, None), 1.0 / p),
        lambda v, p: np.power(np.clip(v, 0, None), p),
        True,
    ),
}


@dataclass(frozen=True)
class CRF:
    """A camera response: a named model (``linear``, ``srgb``, ``gamma`` with
    ``param`` = G so that ``v = x^(1/G)``) or a measured inverse table.

    table : (C, N) float64 or None
        ``gamma^-1`` at each of the ``N`` code values, per channel, monotone, in [0, 1].
    assumed : a default nobody vouched for (no response given: sRGB assumed), not a
        response the user or a measurement supplied
    """

    name: str
    param: float | None = None
    table: np.ndarray | None = field(default=None, compare=False, repr=False)
    assumed: bool = field(default=False, compare=False)
    #: :meth:`codes_table` by grid, each built once per response
    _tables: dict = field(default_factory=dict, init=False, compare=False, repr=False)

    @property
    def is_linear(self) -> bool:
        return self.name == "linear"

    def describe(self) -> str:
        if self.name == "gamma":
            return f"gamma:{self.param:g}"
        return self.name

    def inverse(self, v: np.ndarray, channel: int = 0) -> np.ndarray:
        """``gamma^-1``: normalised code values ``v`` (any shape) -> linear ``x``."""
        if self.table is not None:
            tab = self.table[min(channel, self.table.shape[0] - 1)]
            grid = np.linspace(0.0, 1.0, tab.size)
            return np.interp(v, grid, tab)
        return CRF_MODELS[self.name][1](v, self.param)

    def codes_table(self, n_codes: int, black=0.0, white=None) -> np.ndarray:
        """The paper's ``gamma^-1`` of (2) at every stored code ``r = 0..N-1``: ``(C, N)``
        float64, row ``c`` = :meth:`inverse` of ``clip((r - black_c) / (white_c - black_c),
        0, 1)`` through channel ``c``'s curve.  ``black``, ``white``: scalars or ``(C,)``
        (``white`` default ``N - 1``; ``C`` their length).  The one linearisation of stored
        codes: frames (:meth:`linear`), sample sets
        (:func:`~hdrmerge_cli.core.exposure_estimate.linearise`) and weight tables
        read their linear values from it; built once per response and grid."""
        black = np.atleast_1d(np.asarray(black, dtype=np.float64))
        white = np.broadcast_to(np.asarray(n_codes - 1.0 if white is None else white, dtype=np.float64), black.shape)
        key = (int(n_codes), black.tobytes(), white.tobytes())
        if key not in self._tables:
            r = np.arange(n_codes, dtype=np.float64)
            self._tables[key] = np.stack([self.inverse(np.clip((r - b) / float(w - b), 0.0, 1.0), c)
                                          for c, (b, w) in enumerate(zip(black, white))])
        return self._tables[key]

    def at_codes(self, n_codes: int, black, white) -> CodesInverse:
        """``gamma^-1`` at one frame's stored codes as the merge's tables read it
        (:class:`CodesInverse`): :meth:`codes_table` on the grid of ``n_codes`` codes with
        ``black``, ``white`` per table row, and each row's value half a code above black."""
        black = np.atleast_1d(np.asarray(black, dtype=np.float64))
        white = np.broadcast_to(np.asarray(white, dtype=np.float64), black.shape)
        half = np.array([self.inverse(np.array([0.5 / (w - b)]), c)[0] for c, (b, w) in enumerate(zip(black, white))])
        return CodesInverse(self.codes_table(n_codes, black, white), black, white, half, self.is_linear)

    def linear(self, codes: np.ndarray, n_codes: int, black=0.0, white=None) -> np.ndarray:
        """Linear values (full scale 1, float64 ``(..., C)``) of whole codes ``(..., C)``
        (integers below ``n_codes``) through :meth:`codes_table`."""
        tab = self.codes_table(n_codes, np.broadcast_to(black, codes.shape[-1:]), white)
        return np.stack([tab[c][codes[..., c]] for c in range(codes.shape[-1])], axis=-1)

    def forward(self, x: np.ndarray, channel: int = 0) -> np.ndarray:
        """``gamma``: linear ``x`` in [0, 1] -> normalised code value ``v``."""
        if self.table is not None:
            tab = self.table[min(channel, self.table.shape[0] - 1)]
            grid = np.linspace(0.0, 1.0, tab.size)
            return np.interp(x, tab, grid)
        return CRF_MODELS[self.name][0](x, self.param)


@dataclass(frozen=True)
class CodesInverse:
    """The response's inverse at one frame's stored codes (:meth:`CRF.at_codes`), per table row.

    table : (R, N) float64, ``gamma^-1`` at every stored code ``r = 0..N-1`` (:meth:`CRF.codes_table`)
    black, white : (R,) float64, each row's black and white (clipping) level in stored codes
    half_code : (R,) float64, ``gamma^-1`` half a code value above black
    linear : the response is linear (sensor data)
    """

    table: np.ndarray
    black: np.ndarray
    white: np.ndarray
    half_code: np.ndarray
    linear: bool


def parse_crf(text: str) -> CRF:
    """Parse ``linear``, ``srgb`` or ``gamma:G`` (G > 0) into a :class:`CRF`."""
    name, _, arg = text.strip().lower().partition(":")
    if name not in CRF_MODELS:
        raise HdrMergeError(f"unknown CRF {text!r}: use one of {', '.join(crf_names())}, a CSV table or a profile JSON")
    takes = CRF_MODELS[name][2]
    if takes != bool(arg):
        raise HdrMergeError(f"CRF {text!r}: " + ("gamma needs a value, e.g. gamma:2.2" if takes else f"{name} takes no value"))
    if not takes:
        return CRF(name)
    try:
        p = float(arg)
    except ValueError:
        raise HdrMergeError(f"CRF {text!r}: {arg!r} is not a number") from None
    return gamma_crf(p, f"--crf {text}")


def gamma_crf(p: float, where: str) -> CRF:
    """``gamma:G`` with G in :data:`GAMMA_RANGE`; ``where`` starts the error message."""
    lo, hi = GAMMA_RANGE
    if not (np.isfinite(p) and p > 0):
        raise HdrMergeError(f"{where}: the gamma must be a positive number")
    if not lo <= p <= hi:
        raise HdrMergeError(f"{where}: not a valid response: gamma {p:g} spreads the codes of an 8-bit image over "
                            f"{p * np.log2(255):.3g} stops (cameras' 1.8 to 2.6 over 14 to 21; accepted: gamma "
                            f"{lo:g} to {hi:g})")
    return CRF("gamma", p)


def crf_names() -> list[str]:
    return ["linear", "srgb", "gamma:G"]


def table_crf(table: np.ndarray, name: str = "table") -> CRF:
    """A measured inverse CRF from a ``(C, N)`` or ``(N,)`` table of ``gamma^-1`` values.

    The table is rescaled so that its last entry is 1 (full scale) and must be
    non-decreasing (the paper assumes a monotone, invertible CRF)."""
    tab = np.atleast_2d(np.asarray(table, dtype=np.float64))
    if tab.shape[1] < 2 or not np.all(np.isfinite(tab)):
        raise HdrMergeError("the CRF table needs at least two finite entries per channel")
    if np.any(np.diff(tab, axis=1) < 0):
        raise HdrMergeError("the CRF table is not monotone (gamma^-1 must not decrease with z)")
    if np.any(tab < 0):
        raise HdrMergeError(f"not a valid response: the CRF table has negative values (from {tab.min():g}); "
                            "gamma^-1 is a linear signal, 0 at black")
    top = tab[:, -1:]
    if np.any(top <= 0):
        raise HdrMergeError("the CRF table must end at a positive value")
    return CRF(name, table=tab / top)
