"""Noise parameters given by the user (``--noise``) or found in a profile."""
from __future__ import annotations

from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import NoiseParams

KEYS = ("sigma_o2", "alpha", "beta")


def parse_noise(text: str) -> dict[str, NoiseParams]:
    """``sigma_o2=4,alpha=1,beta=0`` for every channel, or per channel with prefixes
    separated by spaces or ``;``: ``R:sigma_o2=4,alpha=1 G:sigma_o2=3,alpha=1``.
    Returns {channel or "*": NoiseParams}; beta defaults to 0."""
    out = {}
    for group in text.replace(";", " ").split():
        chan, _, body = group.rpartition(":")
        values = {}
        for item in body.split(","):
            key, eq, val = item.partition("=")
            if key.strip() not in KEYS or not eq:
                raise HdrMergeError(f"--noise: {item!r} is not one of {', '.join(k + '=VALUE' for k in KEYS)}")
            try:
                values[key.strip()] = float(val)
            except ValueError:
                raise HdrMergeError(f"--noise: {val!r} is not a number") from None
        if "sigma_o2" not in values or "alpha" not in values:
            raise HdrMergeError("--noise needs at least sigma_o2=... and alpha=...")
        try:
            out[chan.strip().upper() or "*"] = NoiseParams(values["sigma_o2"], values["alpha"], values.get("beta", 0.0))
        except ValueError as exc:
            raise HdrMergeError(f"--noise: {exc}") from None
    if not out:
        raise HdrMergeError("--noise is empty")
    return out


def iso_key(iso: float | None) -> str:
    """A profile's noise key for ``iso``: ``ISO100``, or ``ISO_unknown``."""
    return f"ISO{iso:g}" if iso else "ISO_unknown"


def noise_from_profile(profile: dict, iso: float | None, path: str) -> dict[str, NoiseParams]:
    """The profile's noise entry for ``iso`` (or its only entry): {channel: NoiseParams}."""
    entries = profile.get("noise") or {}
    if not entries:
        raise HdrMergeError(f"{path}: the profile has no noise parameters (run calibrate-noise)")
    key = iso_key(iso)
    if key not in entries:
        if len(entries) != 1:
            raise HdrMergeError(f"{path}: no noise entry for {key} (has {', '.join(entries)})")
        key = next(iter(entries))
    try:
        return {ch.upper(): NoiseParams(float(v["sigma_o2"]), float(v["alpha"]), float(v.get("beta", 0.0)))
                for ch, v in entries[key].items()}
    except (KeyError, TypeError, ValueError) as exc:
        raise HdrMergeError(f"{path}: bad noise entry {key}: {exc}") from None


def per_channel(noise: dict[str, NoiseParams], names: list[str]) -> list[NoiseParams]:
    """Order the parameters by table channel ``names`` (``G2`` falls back to ``G``, any
    channel to ``*``)."""
    out = []
    for name in names:
        for key in (name.upper(), name.upper().rstrip("2"), "*"):
            if key in noise:
                out.append(noise[key])
                break
        else:
            raise HdrMergeError(f"no noise parameters for channel {name} (give {name}:sigma_o2=...,alpha=...)")
    return out


def parse_bounds(text: str) -> tuple[float, float, float]:
    """``--bounds`` for the ``bounded`` weights, on the normalised signal scale:
    ``inv_alpha=0.005,sigma_o2=0.02,beta=0`` (missing ones keep the paper's JPEG values),
    or ``delta=0.1,inv_alpha=0.005`` (fix the clipping-safe width and one bound; the other
    is solved for)."""
    from hdrmerge_cli.core.weights_goossens2012 import BOUNDED_INV_ALPHA, BOUNDED_SIGMA_O2, bounds_for_width

    values = {}
    for item in text.split(","):
        key, eq, val = item.strip().partition("=")
        if key not in ("inv_alpha", "sigma_o2", "beta", "delta") or not eq:
            raise HdrMergeError(f"--bounds: {item!r} is not one of inv_alpha=, sigma_o2=, beta=, delta=")
        try:
            values[key] = float(val)
        except ValueError:
            raise HdrMergeError(f"--bounds: {val!r} is not a number") from None
        if not values[key] >= 0:
            raise HdrMergeError(f"--bounds: {key} must not be negative")
    if "delta" in values:
        try:
            return bounds_for_width(values["delta"], values.get("inv_alpha"), values.get("sigma_o2"),
                                    values.get("beta", 0.0))
        except ValueError as exc:
            raise HdrMergeError(f"--bounds: {exc}") from None
    return (values.get("inv_alpha", BOUNDED_INV_ALPHA), values.get("sigma_o2", BOUNDED_SIGMA_O2),
            values.get("beta", 0.0))
