"""Linear RAW containers (LinearRaw DNG: demosaiced linear RGB), exposure values that count
ISO and aperture, refusals that say what a file is."""
import json
from pathlib import Path

import numpy as np
import pytest

from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.sensor import SensorModel, expose, quantise_raw
from hdrmerge_cli.io.frames import Frame, load_codes, read_frame
from hdrmerge_cli.io.images import read_exr
from benchmarks.input_kinds import write_linear_dng
from hdrmerge_cli.io.metadata import exposure_values, upright

SENSOR = SensorModel(alpha=0.25, sigma_o2=9.0, bits=14, black=512)
H, W = 64, 96
#: camera RGB of white: the as-shot white balance LibRaw reports is its inverse
NEUTRAL = (0.8, 1.0, 1.25)


def _scene() -> np.ndarray:
    """Irradiance (e-/s) ramping over 9 stops left to right, tinted like NEUTRAL (white
    balance makes it grey)."""
    ramp = SENSOR.saturation_electrons * np.geomspace(2.0**-9, 1.0, W) / 0.01
    return np.stack([ramp * n for n in NEUTRAL], axis=-1)[None].repeat(H, axis=0)


def _bracket(folder: Path, times, orientation=1, apertures=None, seed=0) -> list[Path]:
    rng = np.random.default_rng(seed)
    scene, paths = _scene(), []
    for k, t in enumerate(times):
        codes = quantise_raw(expose(scene, t, SENSOR, rng, np.zeros(scene.shape)), SENSOR)
        path = folder / f"lin_{k}.dng"
        write_linear_dng(str(path), codes, black=SENSOR.black, white=SENSOR.white, exposure_time=t, iso=100,
                         aperture=(apertures or [4.0] * len(times))[k], as_shot_neutral=NEUTRAL,
                         orientation=orientation)
        paths.append(path)
    return paths


def test_rawpy_reads_a_linear_dng_as_a_colour_stack(tmp_path):
    """What LibRaw makes of a LinearRaw DNG: no CFA pattern, three colours, a (H, W, 4)
    colour stack (the fourth plane empty) holding the stored values bit-exactly."""
    import rawpy

    codes = np.random.default_rng(1).integers(SENSOR.black, SENSOR.white, (H, W, 3), dtype=np.uint16)
    path = tmp_path / "one.dng"
    write_linear_dng(str(path), codes, black=SENSOR.black, white=SENSOR.white, exposure_time=0.01,
                     as_shot_neutral=NEUTRAL, orientation=6)
    with rawpy.imread(str(path)) as raw:
        assert raw.raw_type == rawpy.RawType.Stack and raw.raw_pattern is None and raw.num_colors == 3
        stack = raw.raw_image_visible
        assert stack.shape == (H, W, 4) and np.array_equal(stack[..., :3], codes) and not stack[..., 3].any()
        assert list(raw.black_level_per_channel[:3]) == [SENSOR.black] * 3 and raw.white_level == SENSOR.white
        assert np.allclose(np.array(raw.camera_whitebalance[:3]) * NEUTRAL, 1.0, rtol=1e-3)
        assert raw.sizes.flip == 6


def test_a_linear_frame_reads_as_linear_rgb_scaled_to_16_bits(tmp_path):
    path = _bracket(tmp_path, [0.01], orientation=6)[0]
    frame = read_frame(path)
    assert (frame.kind, frame.channels, frame.channel_colors, frame.cfa_pattern) == ("linear", 3, "RGB", None)
    assert frame.orientation == 6 and frame.bits == 14
    assert "LinearRaw" in frame.summary()["format"] and frame.summary()["black"] == [512.0] * 3
    assert np.allclose(frame.white_balance, 1 / np.array(NEUTRAL), rtol=1e-3)
    codes = load_codes(frame)
    assert codes.shape == (H, W, 3) and codes.dtype == np.uint16
    import rawpy

    with rawpy.imread(str(path)) as raw:
        stored = raw.raw_image_visible[..., :3].astype(np.float64)
    expected = np.clip(np.rint((stored - 512) * 65535 / (SENSOR.white - 512)), 0, 65535)
    assert np.abs(codes - expected).max() <= 1  # float32 arithmetic: a rounding tie may go either way


def test_info_and_merge_a_linear_dng_bracket(run, tmp_path):
    paths = _bracket(tmp_path, [0.0025, 0.01, 0.04], orientation=6)
    info = json.loads(run("info", *paths, "--json").stdout)
    assert [r["kind"] for r in info["frames"]] == ["linear"] * 3
    assert all("LinearRaw" in r["format"] for r in info["frames"])
    out = tmp_path / "m.exr"
    summary = json.loads(run("merge", *paths, "-o", out, "--preview", tmp_path / "p.png", "--json").stdout)
    assert summary["estimator"] == "ml" and summary["crf"].startswith("linear") and summary["orientation"] == 6
    pixels, attrs = read_exr(str(out))
    assert pixels.shape == (H, W, 3) and attrs["Orientation"] == 6
    # white balanced (green = 1): the tinted ramp is grey, 1.0 = full scale at the reference exposure
    truth = np.geomspace(2.0**-9, 1.0, W) * attrs["hdrmerge:referenceExposure"] / 0.01
    well = slice(W // 3, None)  # the darker third is read noise in every frame
    for c in range(3):
        ratio = pixels[H // 2, well, c] / truth[well]
        assert np.median(np.abs(ratio - 1)) < 0.03, (c, ratio)
    import OpenImageIO as oiio

    spec = oiio.ImageInput.open(str(tmp_path / "p.png")).spec()
    assert (spec.width, spec.height) == (H, W)  # rotated upright (EXIF 6: 90 degrees clockwise)


def test_exposure_values_count_time_iso_and_aperture():
    def frame(t, iso, n):
        return Frame(path="x", kind="raw", width=2, height=2, exposure_time=t, iso=iso, aperture=n, make="",
                     model="", timestamp=None, bits=12, n_codes=65536, black=np.zeros(4), white=np.full(4, 4095.0),
                     channels=4)

    h = exposure_values([frame(0.01, 100, 4.0), frame(0.01, 200, 4.0), frame(0.01, 100, 8.0), frame(0.04, 100, 8.0)])
    assert np.allclose(h, [0.01, 0.02, 0.0025, 0.01])
    # a factor only counts when every frame states it
    assert np.allclose(exposure_values([frame(0.01, 100, None), frame(0.02, None, 8.0)]), [0.01, 0.02])


def test_frames_of_different_apertures_merge_with_a_depth_of_field_warning(run, tmp_path):
    # f/4 at 1/100 s and f/8 at 1/25 s are the same exposure: a burst, merged
    paths = _bracket(tmp_path, [0.0025, 0.01, 0.04], apertures=[4.0, 4.0, 8.0])
    proc = run("merge", *paths, "-o", tmp_path / "m.exr", "--json")
    assert "depth of field" in proc.stderr
    summary = json.loads(proc.stdout)
    assert np.allclose([f["exposure"] for f in summary["frames"]], [0.0025, 0.01, 0.01], rtol=1e-6)
    assert len(summary["equal_exposures"]) == 1


def test_unreadable_raw_kinds_are_refused_in_one_line(run, tmp_path):
    junk = tmp_path / "shot.x3f"
    junk.write_bytes(b"FOVb" + bytes(4000))
    for cmd in ("info", "merge"):
        args = [cmd, junk] + (["-o", tmp_path / "o.exr"] if cmd == "merge" else [])
        proc = run(*args, check=False)
        assert proc.returncode == 1 and "Traceback" not in proc.stderr
        assert proc.stderr.strip().count("\n") == 0 and "Foveon" in proc.stderr and "shot.x3f" in proc.stderr


def test_upright_applies_every_exif_orientation():
    a = np.arange(6).reshape(2, 3)  # stored; the expected views follow the EXIF definitions
    assert np.array_equal(upright(a, 1), a)
    assert np.array_equal(upright(a, 6), [[3, 0], [4, 1], [5, 2]])  # 90 degrees clockwise
    assert np.array_equal(upright(a, 8), [[2, 5], [1, 4], [0, 3]])  # counter-clockwise
    assert np.array_equal(upright(a, 3), [[5, 4, 3], [2, 1, 0]])
    for o in range(1, 9):  # every orientation is a bijection of the pixels
        assert sorted(upright(a, o).ravel()) == list(range(6))


def test_a_linear_dng_without_range_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "bad.dng"  # white level = black level (LibRaw itself refuses it)
    write_linear_dng(str(path), np.zeros((8, 8, 3), np.uint16), black=600, white=600, exposure_time=0.01)
    with pytest.raises(HdrMergeError, match=r"bad\.dng: (white level|not a readable RAW file)"):
        read_frame(path)
