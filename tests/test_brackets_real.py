"""Brackets as cameras shoot them: bursts of equal exposures (merged, noise / N), frames
that disagree with their equal-exposure partner (warned), batch grouping that follows AEB
sequences, and the frames' orientation carried to the output."""
import json
from pathlib import Path

import numpy as np
import pytest

from conftest import SHARED, needs_shared
from hdrmerge_cli.core.repeats import compare_repeat
from hdrmerge_cli.core.sensor import SensorModel, expose, quantise_raw
from hdrmerge_cli.io.frames import Frame
from hdrmerge_cli.io.images import read_exr
from hdrmerge_cli.io.dng_integer import write_dng
from hdrmerge_cli.pipeline.batch import split_brackets

SENSOR = SensorModel(alpha=0.25, sigma_o2=9.0, bits=14, black=512)
#: flat patches (fractions of full scale at the burst's exposure), one per band of columns
LEVELS = (0.05, 0.15, 0.4, 0.7)
H, BAND = 128, 64
T = 0.01


def _write(folder: Path, name: str, scene: np.ndarray, t: float, rng, recorded: float = T) -> Path:
    codes = quantise_raw(expose(scene, t, SENSOR, rng, np.zeros(scene.shape)), SENSOR)
    path = folder / f"{name}.dng"
    write_dng(str(path), codes, pattern="RGGB", black=SENSOR.black, white=SENSOR.white, exposure_time=recorded,
              iso=100)
    return path


def _flat_scene() -> np.ndarray:
    return np.repeat(np.array(LEVELS) * SENSOR.saturation_electrons / T, BAND)[None].repeat(H, axis=0)


@pytest.fixture(scope="module")
def burst(tmp_path_factory):
    folder = tmp_path_factory.mktemp("burst")
    rng = np.random.default_rng(7)
    return [_write(folder, f"b{k}", _flat_scene(), T, rng) for k in range(4)]


def test_a_burst_of_n_equal_exposures_has_1_over_n_of_the_noise_variance(run, tmp_path, burst):
    """N = 4 frames of 1/100 s of a flat scene: the merged image's variance in each flat
    patch is 1/4 of the one-frame merge's (within 10 %): equal exposures are averaged."""
    outs = {}
    for n in (1, len(burst)):
        out = tmp_path / f"m{n}.exr"
        summary = json.loads(run("merge", *burst[:n], "-o", out, "--json").stdout)
        outs[n] = read_exr(str(out))[0]
        if n > 1:  # compared, and found to agree within the noise: no warning
            assert all(e["compared"] and e["outlier_fraction"] < 0.01 and abs(e["ratio_ev"]) < 0.02
                       for e in summary["equal_exposures"])
    m = 8  # away from the bands' edges (the demosaic mixes neighbours)
    for k, level in enumerate(LEVELS):
        patch = (slice(m, -m), slice(k * BAND + m, (k + 1) * BAND - m), 1)
        one, many = outs[1][patch], outs[len(burst)][patch]
        assert abs(np.mean(many) / level - 1) < 0.01
        ratio = np.var(many) / np.var(one)
        assert abs(ratio * len(burst) - 1) < 0.10, (level, ratio)


def test_a_burst_survives_alignment_and_deghosting(run, tmp_path, burst):
    for option in ("--align", "--deghost"):
        proc = run("merge", *burst[:3], "-o", tmp_path / f"{option[2:]}.exr", option, "auto")
        assert "error" not in proc.stderr


@pytest.fixture(scope="module")
def textured(tmp_path_factory):
    """Two frames of a checkerboard at 1/100 s, one exposed 1.5x longer but recorded as
    1/100 s, one of the scene shifted by 8 pixels."""
    folder = tmp_path_factory.mktemp("repeats")
    rng = np.random.default_rng(8)
    yy, xx = np.mgrid[:H, :256]
    scene = (0.1 + 0.5 * ((xx // 16 + yy // 16) % 2)) * SENSOR.saturation_electrons / T
    return {"a": _write(folder, "a", scene, T, rng), "b": _write(folder, "b", scene, T, rng),
            "bright": _write(folder, "bright", scene, 1.5 * T, rng),
            "moved": _write(folder, "moved", np.roll(scene, 8, axis=1), T, rng)}


@pytest.mark.parametrize("odd, words", [(None, None), ("bright", "stops brighter"), ("moved", "beyond the noise")])
def test_equal_exposures_that_disagree_are_merged_with_a_warning(run, tmp_path, textured, odd, words):
    frames = [textured["a"], textured["b"]] + ([textured[odd]] if odd else [])
    proc = run("merge", *frames, "-o", tmp_path / "m.exr", "--align", "off")  # the check of unaligned frames
    warnings = [line for line in proc.stderr.splitlines() if "warning" in line]
    if odd is None:
        assert warnings == []
    else:
        # (the exposure-label check may also flag the brighter frame's label)
        assert any(words in w and f"{odd}.dng" in w for w in warnings), warnings


def test_compare_repeat_measures_ratio_and_outliers():
    rng = np.random.default_rng(0)
    level = rng.uniform(0.05, 0.9, 20000)
    za = level * 4000 + rng.normal(0, 3, level.size)
    zb = level * 4000 + rng.normal(0, 3, level.size)
    same = compare_repeat(za, zb, za / 4000, zb / 4000)
    assert abs(same.ratio_ev) < 0.01 and same.outliers < 1e-3 and not same.content_differs
    zb[:1000] += 400  # 5 % of the samples changed
    moved = compare_repeat(za, zb, za / 4000, zb / 4000)
    assert moved.content_differs and 0.04 < moved.outliers < 0.06
    brighter = compare_repeat(za, 1.2 * za, za / 4000, 1.2 * za / 4000)
    assert brighter.exposure_changed and abs(brighter.ratio_ev - np.log2(1.2)) < 1e-6
    assert compare_repeat(za[:10], zb[:10], za[:10] / 4000, zb[:10] / 4000) is None


# ---------------------------------------------------------------- batch grouping
def _frame(name, t):
    return Frame(path=f"/x/{name}", kind="raw", width=4, height=4, exposure_time=t, iso=100.0, aperture=None,
                 make="Cam", model="One", timestamp=None, bits=12, n_codes=65536, black=np.zeros(4),
                 white=np.full(4, 4095.0), channels=4, cfa_pattern="RGGB")


def _sizes(times):
    frames = [_frame(f"f{k:02d}", t) for k, t in enumerate(times)]
    return [len(b.frames) for b in split_brackets(frames)]


def test_three_aeb_sequences_with_slightly_different_times_are_three_brackets():
    """No timestamps; each ascending 5-frame sequence's times differ slightly from the
    last one's (as cameras round them): the fall back to the short end splits them."""
    base = np.array([1 / 400, 1 / 100, 1 / 25, 1 / 6, 0.6])
    assert _sizes(list(base) + list(base * 1.03) + list(base * 0.97)) == [5, 5, 5]
    # a second scene metered 1 stop darker: no time repeats, the fall still splits
    assert _sizes(list(base) + list(base / 2)) == [5, 5]


def test_centre_out_sequences_and_bursts_stay_whole():
    ev = [0, -1, 1, -2, 2]  # Canon/Sony order 0, -, +, --, ++: its falls of 3 stops are inside one bracket
    times = [0.01 * 2.0**e for e in ev]
    assert _sizes(times + [t * 1.02 for t in times]) == [5, 5]
    assert _sizes([0.01] * 4) == [4]  # a burst: one bracket
    assert _sizes([0.01, 0.01, 0.04, 0.04, 0.16]) == [5]  # a bracket with repeats, each repeated at once
    assert _sizes([0.01, 0.04, 0.16, 0.01, 0.04, 0.16]) == [3, 3]  # the sequence repeats


# ---------------------------------------------------------------- orientation
@needs_shared
def test_portrait_phone_frames_give_an_upright_preview_and_an_oriented_exr(run, tmp_path):
    folder = SHARED / "brackets" / "iphone6_window_jpg"
    frames = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg"))[:2]
    info = json.loads(run("info", *frames, "--json").stdout)
    assert [r["orientation"] for r in info["frames"]] == [6, 6]
    out, preview = tmp_path / "m.exr", tmp_path / "p.jpg"
    run("merge", *frames, "-o", out, "--crf", "srgb", "--preview", preview, "--preview-size", "256")
    import OpenImageIO as oiio

    spec = oiio.ImageInput.open(str(out)).spec()
    assert spec.width > spec.height and spec.get_int_attribute("Orientation") == 6  # stored as shot, tagged
    pv = oiio.ImageInput.open(str(preview)).spec()
    assert pv.height > pv.width and pv.get_int_attribute("Orientation", 1) == 1  # upright pixels
