"""The paper's camera noise model, forward direction: irradiance -> code values.

(16)  x ~ Poisson(t E)                       photo-electrons (exact Poisson here)
(17)  y ~ N(sqrt(alpha) t E, s(t E)),  s(x) = sigma_o^2 + alpha x + beta x^2
(18)  z = gamma(f(y)),  f = clipping to [y_min, y_max], then quantisation to B bits

Units: E in photo-electrons per second per pixel, t in seconds, y and z in code values
(for RAW: above the black level), so ``alpha`` is the squared gain in code values^2 per
electron, ``sigma_o2`` the read-noise variance in code values^2 and ``beta`` the
variance of the gain fixed-pattern noise relative to the mean squared (dimensionless,
times alpha: each pixel's gain is ``sqrt(alpha) (1 + d_i)``, ``d_i ~ N(0, beta / alpha)``,
drawn once and shared by every frame, which gives the ``beta x^2`` term of (17)).
Quantisation adds its own 1/12 code value^2 to the offset variance, which the paper
lumps into ``sigma_o^2``; :attr:`SensorModel.sigma_o2_total` includes it.

ISO (Hasinoff, Durand and Freeman, "Noise-optimal capture for high dynamic range
photography", CVPR 2010, Sec. 3): the ISO setting is an analogue gain ``g = ISO / ISO_base``
applied to the photo-electrons and to the read noise that arises before the amplifier;
the read noise after the amplifier (variance ``sigma_post^2``) is added unamplified, then
the signal is clipped and quantised.  In the code values of (17), with the parameters
given at the base ISO:

    alpha(ISO)    = alpha g^2
    beta(ISO)     = beta g^2
    sigma_o^2(ISO) = (sigma_o^2 - sigma_post^2) g^2 + sigma_post^2

so ``(sigma_o^2 - sigma_post^2) / alpha`` is the pre-amplifier read noise in electrons^2,
the same at every ISO (:meth:`SensorModel.at_iso`).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.noise import noise_variance  # noqa: F401  (s(x) of (17), re-exported)


#: photo-electrons counted at most per pixel and frame: far beyond the saturation of any
#: sensor (full scale / sqrt(alpha) <= 65535 / 1e-6), within NumPy's Poisson sampler
MAX_ELECTRONS = 1e15


@dataclass(frozen=True)
class SensorModel:
    """Parameters of (17) at ISO ``base_iso`` plus the A/D converter: ``bits`` and the
    ``black`` level.  ``sigma_post2`` (code values^2, ``0 <= sigma_post2 <= sigma_o2``) is
    the part of ``sigma_o2`` added after the ISO amplifier (Hasinoff et al. 2010; see the
    module docstring and :meth:`at_iso`)."""

    alpha: float = 0.25
    sigma_o2: float = 9.0
    beta: float = 0.0
    bits: int = 14
    black: int = 512
    sigma_post2: float = 0.0
    base_iso: float = 100.0

    def __post_init__(self):
        if not (self.alpha > 0 and np.isfinite(self.alpha)):
            raise HdrMergeError("alpha (squared gain) must be a positive number")
        if not (np.isfinite(self.sigma_o2) and np.isfinite(self.beta)) or self.sigma_o2 < 0 or self.beta < 0:
            raise HdrMergeError("sigma_o2 and beta must not be negative")
        if not (np.isfinite(self.sigma_post2) and 0 <= self.sigma_post2 <= self.sigma_o2):
            raise HdrMergeError(f"sigma_post2 ({self.sigma_post2:g}) must lie between 0 and sigma_o2 "
                                f"({self.sigma_o2:g}): it is the part of the read noise after the amplifier")
        if not (self.base_iso > 0 and np.isfinite(self.base_iso)):
            raise HdrMergeError("the base ISO must be a positive number")
        if not 2 <= self.bits <= 16:
            raise HdrMergeError("bits must be between 2 and 16")
        if not 0 <= self.black < 2**self.bits - 1:
            raise HdrMergeError("the black level must lie below the white level")

    @property
    def white(self) -> int:
        return 2**self.bits - 1

    @property
    def full_scale(self) -> int:
        """``y_max``: code values between the black and the white level."""
        return self.white - self.black

    @property
    def sigma_o2_total(self) -> float:
        return self.sigma_o2 + 1.0 / 12.0

    @property
    def saturation_electrons(self) -> float:
        return self.full_scale / np.sqrt(self.alpha)

    @property
    def pre_amp_electrons2(self) -> float:
        """Read-noise variance before the amplifier, in electrons^2:
        ``(sigma_o^2 - sigma_post^2) / alpha``, the same at every ISO."""
        return (self.sigma_o2 - self.sigma_post2) / self.alpha

    def at_iso(self, iso: float) -> "SensorModel":
        """The parameters at ISO ``iso`` (Hasinoff et al. 2010), with ``g = iso / base_iso``:
        ``alpha g^2``, ``beta g^2``, ``(sigma_o^2 - sigma_post^2) g^2 + sigma_post^2``;
        ``sigma_post2``, ``bits`` and ``black`` unchanged, ``base_iso = iso`` (so that
        ``at_iso(a).at_iso(b) == at_iso(b)`` up to rounding)."""
        if not (iso > 0 and np.isfinite(iso)):
            raise HdrMergeError(f"ISO {iso}: must be a positive number")
        g2 = (float(iso) / self.base_iso) ** 2
        return replace(self, alpha=self.alpha * g2, beta=self.beta * g2,
                       sigma_o2=(self.sigma_o2 - self.sigma_post2) * g2 + self.sigma_post2, base_iso=float(iso))

    def as_dict(self) -> dict:
        return asdict(self) | {"white": self.white, "sigma_o2_total": self.sigma_o2_total}


def gain_pattern(shape: tuple[int, ...], sensor: SensorModel, rng: np.random.Generator) -> np.ndarray:
    """Per-pixel relative gain deviation ``d_i ~ N(0, beta / alpha)`` (fixed pattern)."""
    if sensor.beta == 0:
        return np.zeros(shape)
    return rng.normal(0.0, np.sqrt(sensor.beta / sensor.alpha), shape)


def expose(
    irradiance: np.ndarray, time: float, sensor: SensorModel, rng: np.random.Generator, pattern: np.ndarray
) -> np.ndarray:
    """Linear signal ``y`` (code values above black, unclipped, float64) of one exposure:
    Poisson photon counts (16), gain with fixed pattern and Gaussian read noise (17).

    At ISO ``k`` pass ``sensor.at_iso(k)``: one Gaussian of variance ``sigma_o^2(ISO)``
    has the distribution of the pre-amplifier read noise amplified by ``g`` plus the
    post-amplifier read noise (Hasinoff et al. 2010), except that the gain fixed pattern
    ``(1 + d_i)`` multiplies the photo-electrons only, not the pre-amplifier read noise
    (a difference of order ``beta / alpha`` in the read noise's variance)."""
    electrons = rng.poisson(np.minimum(np.asarray(irradiance, dtype=np.float64) * time, MAX_ELECTRONS))
    y = np.sqrt(sensor.alpha) * electrons * (1.0 + pattern)
    if sensor.sigma_o2 > 0:
        y += rng.normal(0.0, np.sqrt(sensor.sigma_o2), y.shape)
    return y


def quantise_raw(y: np.ndarray, sensor: SensorModel) -> np.ndarray:
    """RAW code values (18) with an identity CRF: ``round(y) + black`` clipped to
    ``[0, white]`` (values below black are kept, as real sensors do), uint16."""
    return np.clip(np.rint(y) + sensor.black, 0, sensor.white).astype(np.uint16)


def quantise_crf(y: np.ndarray, sensor: SensorModel, crf: CRF, out_bits: int) -> np.ndarray:
    """Camera-processed code values (18): the linear ADC output ``f(y)`` (black already
    subtracted, ``bits``-bit) goes through the CRF and is re-quantised to ``out_bits``."""
    f = np.clip(np.rint(y), 0, sensor.full_scale) / sensor.full_scale
    v = np.stack([crf.forward(f[..., c], c) for c in range(f.shape[-1])], axis=-1) if f.ndim == 3 else crf.forward(f)
    z = np.rint(np.clip(v, 0.0, 1.0) * (2**out_bits - 1))
    return z.astype(np.uint8 if out_bits <= 8 else np.uint16)


def auto_exposure_times(
    irradiance: np.ndarray, sensor: SensorModel, frames: int, dark_percentile: float = 1.0, bright_percentile: float = 99.95
) -> np.ndarray:
    """Exposure times (s, increasing, log-spaced) that cover a scene: the shortest puts
    the ``bright_percentile`` irradiance at 90 % of saturation, the longest puts the
    ``dark_percentile`` irradiance at 25 % of saturation."""
    lo, hi = np.percentile(irradiance, [dark_percentile, bright_percentile])
    lo = max(lo, hi * 1e-9, np.finfo(float).tiny)
    sat = sensor.saturation_electrons
    t_min, t_max = 0.9 * sat / hi, 0.25 * sat / lo
    if frames == 1:
        return np.array([np.sqrt(t_min * t_max)])
    t_max = max(t_max, t_min * 2.0 ** (frames - 1))  # at least one stop apart
    return np.geomspace(t_min, t_max, frames)
