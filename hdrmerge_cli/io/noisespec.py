"""Noise parameters given by the user (``--noise``) or found in a profile, and the
``--bounds`` of the bounded weights: every value is checked here, once."""
from __future__ import annotations

import math
import re

from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import NoiseParams, per_channel  # noqa: F401  (per_channel re-exported)
from hdrmerge_cli.io.times import parse_number

KEYS = ("sigma_o2", "alpha", "beta")

#: accepted range of each noise parameter (code values^2; alpha per electron): wide
#: enough for any sensor, narrow enough that (17) cannot overflow
NOISE_RANGES = {"sigma_o2": (0.0, 1e12), "alpha": (1e-12, 1e12), "beta": (0.0, 1e12)}

_CHANNEL = re.compile(r"[A-Z][A-Z0-9]{0,7}", re.ASCII)


def noise_params(values: dict, where: str) -> NoiseParams:
    """:class:`NoiseParams` from ``{"sigma_o2": .., "alpha": .., "beta": ..}`` (beta
    optional, default 0), each a finite number (not a string or boolean) within
    :data:`NOISE_RANGES`; ``where`` starts the error message."""
    checked = {}
    for key in KEYS:
        value = values.get(key, 0.0 if key == "beta" else None)
        if value is None:
            raise HdrMergeError(f"{where}: {key} is missing (need sigma_o2 and alpha, optionally beta)")
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise HdrMergeError(f"{where}: {key} must be a number, not {str(value)[:40]!r}")
        lo, hi = NOISE_RANGES[key]
        if not (math.isfinite(value) and lo <= value <= hi):
            raise HdrMergeError(f"{where}: {key} = {value:g} is outside [{lo:g}, {hi:g}]")
        checked[key] = float(value)
    return NoiseParams(**checked)


def _assignments(text: str, keys, option: str) -> dict[str, float]:
    """``key=number,key=number`` -> {key: float}, each key of ``keys`` at most once."""
    values = {}
    for item in text.split(","):
        key, eq, val = (part.strip() for part in item.partition("="))
        if key not in keys or not eq:
            raise HdrMergeError(f"{option}: {item[:40]!r} is not one of {', '.join(k + '=VALUE' for k in keys)}")
        if key in values:
            raise HdrMergeError(f"{option}: {key} is given twice")
        try:
            values[key] = parse_number(val)
        except HdrMergeError as exc:
            raise HdrMergeError(f"{option}: {key}: {exc}") from None
    return values


def parse_noise(text: str) -> dict[str, NoiseParams]:
    """``sigma_o2=4,alpha=1,beta=0`` for every channel, or per channel with prefixes
    separated by spaces or ``;``: ``R:sigma_o2=4,alpha=1 G:sigma_o2=3,alpha=1``.
    Returns {channel or "*": NoiseParams} (:func:`noise_params`: code values^2, beta
    defaults to 0); an empty text, a repeated channel or key is an error."""
    out = {}
    for group in text.replace(";", " ").split():
        chan, _, body = group.rpartition(":")
        chan = chan.strip().upper() or "*"
        if chan != "*" and not _CHANNEL.fullmatch(chan):
            raise HdrMergeError(f"--noise: {chan[:40]!r} is not a channel name (R, G, B, G2, Y, ...)")
        if chan in out:
            raise HdrMergeError(f"--noise: channel {chan} is given twice")
        out[chan] = noise_params(_assignments(body, KEYS, "--noise"), "--noise" + ("" if chan == "*" else f" {chan}"))
    if not out:
        raise HdrMergeError("--noise: empty value (give sigma_o2=...,alpha=...)")
    return out


def iso_key(iso: float | None) -> str:
    """A profile's noise key for ``iso``: ``ISO100``, or ``ISO_unknown``."""
    return f"ISO{iso:g}" if iso else "ISO_unknown"


def iso_of_key(key: str) -> float | None:
    """The ISO of a profile's noise key (``ISO400`` -> 400), None for ``ISO_unknown``."""
    try:
        iso = float(key[3:]) if key.startswith("ISO") else None
    except ValueError:
        return None
    return iso if iso is not None and iso == iso and 0 < iso < float("inf") else None


def noise_from_profile(profile: dict, iso: float | None, path: str) -> dict[str, NoiseParams]:
    """The profile's noise entry for ``iso`` (or its only entry): {channel: NoiseParams},
    each channel's numbers checked by :func:`noise_params`."""
    entries = profile.get("noise") or {}
    if not entries:
        raise HdrMergeError(f"{path}: the profile has no noise parameters (run calibrate-noise)")
    key = iso_key(iso)
    if key not in entries:
        if len(entries) != 1:
            raise HdrMergeError(f"{path}: no noise entry for {key} (has {', '.join(repr(k[:20]) for k in entries)})")
        key = next(iter(entries))
    entry = entries[key]
    if not isinstance(entry, dict) or not entry:
        raise HdrMergeError(f"{path}: noise entry {key[:20]!r} must be an object of channels with sigma_o2, alpha, beta")
    out = {}
    for ch, v in entry.items():
        if not isinstance(v, dict):
            raise HdrMergeError(f"{path}: noise entry {key[:20]!r}, channel {ch[:20]!r}: must be an object with "
                                "sigma_o2, alpha, beta")
        out[ch.upper()] = noise_params(v, f"{path}: noise entry {key[:20]!r}, channel {ch[:20]!r}")
    return out


#: accepted range of each ``--bounds`` value (normalised signal scale, full scale = 1)
BOUNDS_RANGES = {"inv_alpha": (1e-9, 1e3), "sigma_o2": (1e-9, 1e3), "beta": (0.0, 1e3), "delta": (1e-6, 1 - 1e-6)}


def parse_bounds(text: str) -> tuple[float, float, float]:
    """``--bounds`` for the ``bounded`` weights, on the normalised signal scale:
    ``inv_alpha=0.005,sigma_o2=0.02,beta=0`` (missing ones keep the paper's JPEG values),
    or ``delta=0.1,inv_alpha=0.005`` (fix the clipping-safe width and one bound; the other
    is solved for).  Each value must lie in :data:`BOUNDS_RANGES` (the bounds positive,
    beta >= 0, delta a fraction of full scale).  Returns ``(inv_alpha, sigma_o2, beta)``."""
    from hdrmerge_cli.core.weights_goossens2012 import BOUNDED_INV_ALPHA, BOUNDED_SIGMA_O2, bounds_for_width

    values = _assignments(text, tuple(BOUNDS_RANGES), "--bounds")
    for key, value in values.items():
        lo, hi = BOUNDS_RANGES[key]
        if not lo <= value <= hi:
            raise HdrMergeError(f"--bounds: {key} = {value:g} is outside [{lo:g}, {hi:g}]")
    if "delta" in values:
        try:
            return bounds_for_width(values["delta"], values.get("inv_alpha"), values.get("sigma_o2"),
                                    values.get("beta", 0.0))
        except (ValueError, ArithmeticError, RuntimeError) as exc:
            raise HdrMergeError(f"--bounds: {exc}") from None
    return (values.get("inv_alpha", BOUNDED_INV_ALPHA), values.get("sigma_o2", BOUNDED_SIGMA_O2),
            values.get("beta", 0.0))
