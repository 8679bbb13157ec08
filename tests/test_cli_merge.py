"""End-to-end: the installed command on simulated brackets with known ground truth and
on the real brackets in ../shared/data."""
import json

import numpy as np
import pytest

from conftest import SHARED, frames_of, log_rmse, needs_shared
from hdrmerge_cli.core.cfa import mosaic
from hdrmerge_cli.io.images import read_exr


def _merge(run, tmp_path, inputs, *args, name="out.exr"):
    out = tmp_path / name
    proc = run("merge", *inputs, "-o", out, "--json", *args)
    return out, json.loads(proc.stdout)


def test_dng_bracket_cfa_merge_matches_truth_and_more_frames_help(run, tmp_path, dng_bracket):
    folder, meta = dng_bracket
    truth, _ = read_exr(folder / "truth.exr")
    truth_cfa = mosaic(truth, meta["cfa_pattern"])
    ref = str(meta["reference_exposure"])
    errors = {}
    for which in [(0, 2, 4), (0, 1, 2, 3, 4)]:
        out, summary = _merge(run, tmp_path, frames_of(folder, meta, which), "--cfa", "--reference", ref,
                              name=f"cfa{len(which)}.exr")
        pixels, attrs = read_exr(out)
        assert attrs["channelnames"] == ("Y",) and np.all(np.isfinite(pixels))
        errors[len(which)] = log_rmse(pixels[..., 0], truth_cfa)
    # 14-bit RAW, 5 frames: 1.7 % log error measured at release; the bound leaves room
    assert errors[5] < 0.03
    assert errors[5] < errors[3]


def test_dng_bracket_demosaiced_rec709_output(run, tmp_path, dng_bracket):
    folder, meta = dng_bracket
    truth, _ = read_exr(folder / "truth.exr")
    out, summary = _merge(run, tmp_path, frames_of(folder, meta), "--extra-channels", "clipped,weight")
    pixels, attrs = read_exr(out)
    assert attrs["channelnames"] == ("R", "G", "B", "clipped", "weight")
    assert np.all(np.isfinite(pixels))
    assert attrs["hdrmerge:referenceExposure"] == pytest.approx(meta["reference_exposure"], rel=1e-5)
    assert len(attrs["chromaticities"]) == 8
    # demosaicing errs at sharp edges; the median pixel must be accurate
    err = np.abs(np.log(np.clip(pixels[4:-4, 4:-4, :3], 1e-12, None)) - np.log(truth[4:-4, 4:-4]))
    assert np.median(err) < 0.02
    assert set(summary["timing_seconds"]) >= {"decode", "merge", "color_and_write"}
    assert summary["frames"][0]["exposure_time"] < summary["frames"][-1]["exposure_time"]
    profile = json.loads((tmp_path / "out.profile.json").read_text())
    assert profile["schema"] == 1 and profile["crf"] == {"model": "linear"}


#: log-RMSE bounds, about 1.5 x what each classical weighting measured on this bracket
#: (triangle 0.141, mann 0.126, deneve 0.354, gaussian 0.100, uniform 0.428).  Without
#: the variance factor of (7), weights in the gamma-encoded code domain trust the dark,
#: noisy codes of short frames: that bias is what the paper's noise model removes.
TIFF_BOUNDS = {"triangle": 0.21, "mann": 0.19, "deneve": 0.53, "gaussian": 0.15, "uniform": 0.64}


@pytest.mark.parametrize("weights", sorted(TIFF_BOUNDS))
def test_tiff16_bracket_every_weighting(run, tmp_path, tiff_bracket, weights):
    folder, meta = tiff_bracket
    truth, _ = read_exr(folder / "truth.exr")
    out, _ = _merge(run, tmp_path, frames_of(folder, meta), "--crf", "gamma:2.2", "--weights", weights)
    pixels, _ = read_exr(out)
    assert log_rmse(pixels, truth) < TIFF_BOUNDS[weights]
    assert np.median(np.abs(np.log(pixels) - np.log(truth))) < 0.15


def test_jpeg_bracket_with_known_crf_and_half_output(run, tmp_path, jpeg_bracket):
    folder, meta = jpeg_bracket
    truth, _ = read_exr(folder / "truth.exr")
    out, summary = _merge(run, tmp_path, frames_of(folder, meta), "--crf", "srgb", "--half")
    pixels, attrs = read_exr(out)
    assert np.all(np.isfinite(pixels))
    # measured 0.050: 8-bit codes 8 stops apart; the dark end reads ~9 % high because
    # triangle weights trust the short frames' noisy codes (no variance factor yet)
    assert np.median(np.abs(np.log(pixels) - np.log(truth))) < 0.08


def test_jpeg_without_crf_measures_it_or_says_why_srgb_is_assumed(run, tmp_path, jpeg_bracket):
    """No --crf: the response is measured on the bracket (no warning); a single frame cannot
    pin it, and sRGB is assumed with the reason and the advice."""
    folder, meta = jpeg_bracket
    proc = run("merge", *frames_of(folder, meta), "-o", tmp_path / "x.exr")
    assert "warning" not in proc.stderr and proc.stdout == "", proc.stderr
    proc = run("merge", *frames_of(folder, meta, [1]), "-o", tmp_path / "y.exr")
    assert "none can be measured" in proc.stderr and "estimate-crf" in proc.stderr and "sRGB" in proc.stderr


def test_times_override_and_times_file(run, tmp_path, jpeg_bracket):
    folder, meta = jpeg_bracket
    files = frames_of(folder, meta)
    times = ",".join(f"{t:.9g}" for t in meta["exposure_times"])
    _, s1 = _merge(run, tmp_path, files, "--crf", "srgb", "--times", times, name="a.exr")
    tf = tmp_path / "times.txt"
    tf.write_text("# name seconds\n" + "\n".join(f"{f.name} {t:.9g}" for f, t in zip(files, meta["exposure_times"])))
    _, s2 = _merge(run, tmp_path, files[::-1], "--crf", "srgb", "--times-file", tf, name="b.exr")
    assert [f["path"] for f in s1["frames"]] == [f["path"] for f in s2["frames"]]
    a, _ = read_exr(tmp_path / "a.exr")
    b, _ = read_exr(tmp_path / "b.exr")
    np.testing.assert_allclose(a, b, rtol=1e-6)


@needs_shared
@pytest.mark.parametrize("bracket", ["office_jpg", "stack_jpg", "stack_ghost_jpg", "stack_handheld_jpg"])
def test_real_jpeg_brackets(run, tmp_path, bracket):
    files = sorted(p for p in (SHARED / "brackets" / bracket).iterdir() if p.suffix.lower() == ".jpg")
    out, summary = _merge(run, tmp_path, files)
    pixels, _ = read_exr(out)
    assert np.all(np.isfinite(pixels)) and pixels.min() >= 0
    # frames come out sorted by exposure, and their brightness rises with exposure
    from hdrmerge_cli.io.frames import load_codes, read_frame

    means = [load_codes(read_frame(f["path"])).mean() for f in summary["frames"]]
    assert means == sorted(means)
    times = [f["exposure_time"] for f in summary["frames"]]
    assert times == sorted(times)


@needs_shared
def test_real_dng_decodes_with_its_black_and_white_levels(run, tmp_path):
    from hdrmerge_cli.io.frames import load_codes, read_frame

    frame = read_frame(SHARED / "raw" / "colorchart.dng")
    assert frame.kind == "raw" and frame.cfa_pattern == "RGGB"
    assert frame.black.tolist() == [2056.0] * 4 and frame.white[0] == 15000
    codes = load_codes(frame)
    assert codes.shape == (frame.height, frame.width) == (1156, 1734)
    assert 1900 < np.median(codes[codes < 2056 + 200]) < 2200  # dark pixels sit on the black level
    out, summary = _merge(run, tmp_path, [SHARED / "raw" / "colorchart.dng"])
    pixels, _ = read_exr(out)
    assert pixels.shape == (1156, 1734, 3) and np.all(np.isfinite(pixels))


NOISE_DNG = "sigma_o2=9.083,alpha=0.25"  # the simulated sensor's (quantisation included)


@pytest.mark.parametrize("args", [
    ("--weights", "probabilistic", "--noise", NOISE_DNG, "--estimator", "log"),
    ("--weights", "direct", "--noise", NOISE_DNG, "--estimator", "ml"),
    ("--weights", "optimal", "--noise", NOISE_DNG),
    ("--weights", "direct", "--noise", NOISE_DNG, "--irls", "5"),
    ("--weights", "triangle", "--variance", "model", "--noise", "R:" + NOISE_DNG + " G:" + NOISE_DNG + " B:" + NOISE_DNG),
])
def test_noise_model_merges_of_the_dng_bracket(run, tmp_path, dng_bracket, args):
    folder, meta = dng_bracket
    truth_cfa = mosaic(read_exr(folder / "truth.exr")[0], meta["cfa_pattern"])
    out, s = _merge(run, tmp_path, frames_of(folder, meta), "--cfa", "--reference", str(meta["reference_exposure"]),
                    *args)
    pixels, attrs = read_exr(out)
    assert log_rmse(pixels[..., 0], truth_cfa) < 0.03
    assert s["noise"]["R"]["alpha"] == 0.25 and attrs["hdrmerge:variance"] == s["variance"]
    if "--irls" in args:
        assert 1 <= s["irls_iterations"] <= 5  # stops early once the estimate settles
    profile = json.loads((tmp_path / "out.profile.json").read_text())
    assert profile["noise"]["used"]["G"]["sigma_o2"] == pytest.approx(9.083)


def test_merge_takes_noise_from_a_calibrated_profile(run, tmp_path, dng_bracket):
    folder, meta = dng_bracket
    prof = tmp_path / "cam.json"
    run("calibrate-noise", *frames_of(folder, meta), "-o", prof)
    _, s = _merge(run, tmp_path, frames_of(folder, meta), "--profile", prof, "--weights", "direct")
    assert s["variance"] == "model" and s["estimator"] == "ml" and s["noise"]["G2"]["alpha"] > 0


def test_bounded_needs_no_noise_parameters(run, tmp_path, jpeg_bracket):
    folder, meta = jpeg_bracket
    out, s = _merge(run, tmp_path, frames_of(folder, meta), "--crf", "srgb", "--weights", "bounded",
                    "--estimator", "log", "--variance", "codes")
    assert s["weights"] == "bounded" and s["variance"] == "codes" and np.all(np.isfinite(read_exr(out)[0]))


@pytest.mark.parametrize("args,message", [
    (("--noise", "sigma_o2=4"), "alpha"),
    (("--noise", "sigma_o2=4,alpha=-1"), "alpha"),
    (("--noise", "gain=2"), "sigma_o2"),
    (("--weights", "direct", "--noise", "sigma_o2=1e9,alpha=1"), "clipping-safe"),
])
def test_noise_option_errors(run, tmp_path, jpeg_bracket, args, message):
    folder, meta = jpeg_bracket
    proc = run("merge", *frames_of(folder, meta), "--crf", "srgb", "-o", tmp_path / "e.exr", *args, check=False)
    assert proc.returncode == 1 and message in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "e.exr").exists()


def test_bounded_with_user_bounds_and_bad_bounds(run, tmp_path, jpeg_bracket):
    folder, meta = jpeg_bracket
    out, s = _merge(run, tmp_path, frames_of(folder, meta), "--crf", "srgb", "--weights", "bounded",
                    "--bounds", "delta=0.3,inv_alpha=0.002")
    assert s["bounds"][0] == 0.002 and 0 < s["bounds"][1] < 0.02
    proc = run("merge", *frames_of(folder, meta), "--crf", "srgb", "--weights", "bounded", "--bounds", "delta=0.5",
               "-o", tmp_path / "x.exr", check=False)
    assert proc.returncode == 1 and "--bounds" in proc.stderr and not (tmp_path / "x.exr").exists()


def test_a_20_stop_bracket(run, tmp_path):
    """Six 14-bit frames 4 stops apart (2^-10 .. 2^10 s): finite output, measured pixels
    accurate, the unmeasured ones flagged."""
    folder = tmp_path / "b20"
    times = ",".join(f"{2.0 ** e:.10g}" for e in range(-10, 11, 4))
    run("simulate", "-o", folder, "--size", "128x96", "--times", times, "--scale", "1e-3", "-q")
    meta = json.loads((folder / "simulation.json").read_text())
    out, s = _merge(run, tmp_path, frames_of(folder, meta), "--cfa", "--weights", "direct", "--noise", NOISE_DNG,
                    "--reference", str(meta["reference_exposure"]), "--extra-channels", "clipped")
    pixels, _ = read_exr(out)
    assert np.all(np.isfinite(pixels)) and len(s["frames"]) == 6
    truth = mosaic(read_exr(folder / "truth.exr")[0], "RGGB")
    ok = pixels[..., 1] == 0
    assert ok.mean() > 0.95 and log_rmse(pixels[..., 0][ok], truth[ok]) < 0.05


def test_float_images_are_refused_in_one_line(run, tmp_path):
    import OpenImageIO as oiio

    f = tmp_path / "float.tif"
    spec = oiio.ImageSpec(8, 6, 3, "float")
    spec.attribute("ExposureTime", 0.01)
    o = oiio.ImageOutput.create(str(f))
    o.open(str(f), spec)
    o.write_image(np.ones((6, 8, 3), np.float32))
    o.close()
    proc = run("merge", f, "-o", tmp_path / "x.exr", check=False)
    assert proc.returncode == 1 and "float.tif" in proc.stderr and "8- or 16-bit" in proc.stderr


def test_strip_demosaic_equals_whole_frame(monkeypatch):
    """The EXR is made in strips of rows with a halo: strips must join seamlessly."""
    import hdrmerge_cli.pipeline.output as pm
    from hdrmerge_cli.io.frames import Frame

    frame = Frame(path="x", kind="raw", width=40, height=30, exposure_time=1.0, iso=None, aperture=None, make="",
                  model="", timestamp=None, bits=12, n_codes=65536, black=np.zeros(4), white=np.full(4, 4095.0),
                  channels=4, cfa_pattern="RGGB")
    frame.white_balance = np.array([2.0, 1.0, 1.5])
    frame.color_matrix = np.eye(3) + 0.1
    mosaic = np.random.default_rng(0).random((30, 40)).astype(np.float32)
    whole = pm._raw_to_rgb_rows(mosaic, frame, 0, 30)
    parts = np.concatenate([pm._raw_to_rgb_rows(mosaic, frame, y, min(30, y + 6)) for y in range(0, 30, 6)])
    np.testing.assert_allclose(parts, whole, rtol=1e-5, atol=1e-6)


def test_prefetched_keeps_order_bounds_the_lookahead_and_raises():
    """Strips come back in order, computed at most ``ahead`` in advance; a failing strip
    raises in the consumer."""
    import threading

    from hdrmerge_cli.pipeline.output import prefetched

    started, lock = [], threading.Lock()

    def fn(i):
        with lock:
            started.append(i)
        return i * i

    seen = []
    for k, v in enumerate(prefetched(fn, range(20), ahead=2)):
        with lock:
            assert max(started) <= k + 2  # never more than `ahead` strips beyond the one consumed
        seen.append(v)
    assert seen == [i * i for i in range(20)]

    def bad(i):
        if i == 3:
            raise ValueError("strip 3")
        return i

    with pytest.raises(ValueError, match="strip 3"):
        list(prefetched(bad, range(10)))


def test_block_mean_of_strips_equals_the_whole_image_block_mean():
    from hdrmerge_cli.core.preview import BlockMean, block_factor

    img = np.random.default_rng(4).random((37, 50, 3))
    f = block_factor(37, 50, 16)
    assert f == 4
    acc = BlockMean(37, 50, 3, f)
    for y0, y1 in ((0, 5), (5, 19), (19, 37)):  # strips that cut through blocks
        acc.add(y0, img[y0:y1])
    want = img[:36, :48].reshape(9, 4, 12, 4, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(acc.result(), want, rtol=1e-12)
    assert block_factor(37, 50, 0) == 1 and block_factor(37, 50, 4000) == 1


def test_tonemap_is_monotone_srgb_and_black_stays_black():
    from hdrmerge_cli.core.preview import tonemap_srgb

    ramp = np.geomspace(1e-3, 1e3, 64)[None, :, None].repeat(3, axis=2)
    out = tonemap_srgb(ramp)
    assert out.dtype == np.uint8 and out.shape == ramp.shape
    assert np.all(np.diff(out[0, :, 1].astype(int)) >= 0) and out[0, -1, 1] > out[0, 0, 1] + 100
    assert not tonemap_srgb(np.zeros((2, 2, 3))).any()


def test_reinhard_devlin_equals_colour_hdri():
    """The preview's operator against colour-hdri's tonemapping_operator_Reinhard2004 and
    colour's sRGB encoding (defaults; an HDR image over 8 decades, coloured)."""
    from benchmarks import quiet_import
    from hdrmerge_cli.core.preview import reinhard_devlin, tonemap_srgb

    rng = np.random.default_rng(2)
    rgb = np.exp(rng.uniform(-9, 9, (20, 30, 1))) * rng.uniform(0.2, 1.0, (20, 30, 3))
    ref = quiet_import("colour_hdri").tonemapping_operator_Reinhard2004(rgb)
    np.testing.assert_allclose(reinhard_devlin(rgb), ref, rtol=1e-12)
    encoded = quiet_import("colour.models").eotf_inverse_sRGB(np.clip(ref, 0, 1))
    np.testing.assert_array_equal(tonemap_srgb(rgb), np.rint(np.clip(encoded, 0, 1) * 255).astype(np.uint8))


def test_merge_writes_a_preview_with_the_exr(run, tmp_path, dng_bracket):
    import OpenImageIO as oiio

    folder, meta = dng_bracket
    out, pic = tmp_path / "m.exr", tmp_path / "m.jpg"
    s = json.loads(run("merge", *frames_of(folder, meta), "-o", out, "--preview", pic, "--preview-size", "100",
                       "--json").stdout)
    assert s["preview"] == str(pic)
    spec = oiio.ImageInput.open(str(pic)).spec()
    assert (spec.width, spec.height, spec.nchannels) == (256 // 3, 192 // 3, 3)  # factor ceil(256 / 100) = 3
    said = run("merge", *frames_of(folder, meta), "-o", out, "--preview", pic, "--overwrite").stderr
    assert f"wrote {out}, {tmp_path / 'm.profile.json'} and {pic}" in said  # the preview is named too
    proc = run("merge", *frames_of(folder, meta), "-o", tmp_path / "n.exr", "--preview", tmp_path / "n.exr.gif",
               check=False)
    assert proc.returncode == 1 and "n.exr.gif" in proc.stderr and not (tmp_path / "n.exr").exists()


def test_default_weights_follow_the_estimator(run, tmp_path, dng_bracket, jpeg_bracket):
    """--weights auto: uniform for the ML estimator (RAW), triangle for the log one;
    --irls unset: one pass for the ML estimator."""
    folder, meta = dng_bracket
    _, s = _merge(run, tmp_path, frames_of(folder, meta), "--cfa")
    assert (s["weights"], s["estimator"]) == ("uniform", "ml")
    assert s["irls_iterations"] == 1  # one re-weighting at the merged estimate (the ML default)
    _, s = _merge(run, tmp_path, frames_of(folder, meta), "--cfa", "--estimator", "log", "--overwrite")
    assert (s["weights"], s["estimator"], s["irls_iterations"]) == ("triangle", "log", 0)
    folder, meta = jpeg_bracket
    _, s = _merge(run, tmp_path, frames_of(folder, meta), "--crf", "srgb", "--overwrite")
    assert (s["weights"], s["estimator"]) == ("triangle", "log")


def test_image_defaults_pick_the_estimator_by_the_variance_beyond_the_noise_model(run, tmp_path, jpeg_bracket,
                                                                                   tiff_bracket):
    """Images: the noise and the variance beyond it are measured on the bracket.  JPEG
    frames (compression and 8-bit rounding the model does not hold) keep the excess: the
    log estimator with triangle weights and code-error variances.  16-bit TIFFs of a
    simulated sensor (a raw converter's output: nothing beyond the model) pass the test:
    the ML estimator with the noise model.  Asking for the ML estimator or a noise-model
    weighting uses the measured noise instead of the conservative bounds."""
    folder, meta = jpeg_bracket
    frames = frames_of(folder, meta)
    out, s = _merge(run, tmp_path, frames, "--crf", "srgb")
    assert s["noise_source"].startswith("measured on the bracket") and "excess_variance" in s["timing_seconds"]
    excess = json.loads(out.with_suffix(".profile.json").read_text())["excess_variance"]
    assert excess["tested"] and excess["kept"] and excess["chi_model"] > 2
    assert (s["estimator"], s["weights"], s["variance"]) == ("log", "triangle", "codes")
    for args in (("--estimator", "ml"), ("--weights", "probabilistic"), ("--variance", "model"), ("--irls", "2")):
        proc = run("merge", *frames, "--crf", "srgb", "-o", tmp_path / "m.exr", "--json", "--overwrite", *args)
        s = json.loads(proc.stdout)
        assert s["noise_source"].startswith("measured on the bracket")
        assert "bounded scheme" not in proc.stderr
    est, _ = read_exr(tmp_path / "m.exr")
    truth, _ = read_exr(folder / "truth.exr")
    assert np.isfinite(est).all() and log_rmse(est, truth) < 0.5
    folder, meta = tiff_bracket
    out, s = _merge(run, tmp_path, frames_of(folder, meta), "--crf", "gamma:2.2", name="tif.exr")
    excess = json.loads(out.with_suffix(".profile.json").read_text())["excess_variance"]
    assert excess["tested"] and not excess["kept"] and excess["levels_sd"] == [0.0] * len(excess["levels_sd"])
    assert (s["estimator"], s["weights"], s["variance"]) == ("ml", "uniform", "model")


def test_outputs_the_tool_cannot_write_faithfully_are_refused(run, tmp_path, jpeg_bracket):
    """No silently wrong result: a non-EXR output, a --reference that underflows or
    overflows the output type, an all-zero weight table; one line, nothing written."""
    folder, meta = jpeg_bracket
    frames = frames_of(folder, meta)
    lut = tmp_path / "zero.csv"
    run("weights-lut", *frames, "--crf", "srgb", "-o", lut)
    rows = lut.read_text().splitlines()
    lut.write_text("\n".join([rows[0]] + [",".join([r.split(",")[0]] + ["0"] * (len(r.split(",")) - 1))
                                         for r in rows[1:]]) + "\n")  # z kept, every weight zero
    for args, words in [(("-o", tmp_path / "x.jpg"), "OpenEXR (*.exr) or"),
                        (("-o", tmp_path / "x.exr", "--half", "--reference", "1e-8"), "--reference"),
                        (("-o", tmp_path / "x.exr", "--half", "--reference", "1e5"), "drop --half"),
                        (("-o", tmp_path / "x.exr", "--lut", lut), "all zero")]:
        proc = run("merge", *frames, "--crf", "srgb", *args, check=False)
        assert proc.returncode == 1 and words in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1
    assert not list(tmp_path.glob("x*"))


def test_a_response_table_that_does_not_cover_the_codes_is_refused(run, tmp_path, jpeg_bracket):
    folder, meta = jpeg_bracket
    csv = tmp_path / "short.csv"
    csv.write_text("z,linear\n0,0\n100,1\n")
    proc = run("merge", *frames_of(folder, meta), "--crf", csv, "-o", tmp_path / "x.exr", check=False)
    assert proc.returncode == 1 and "covers codes 0..100" in proc.stderr and "0..255 (8-bit)" in proc.stderr
    assert not (tmp_path / "x.exr").exists()


def test_a_frame_with_another_picture_style_keeps_the_excess(run, tmp_path, tiff_bracket):
    """The 16-bit TIFF bracket the model explains, with one frame through another tone
    curve (another picture style: codes v -> v^0.8): the pairs show the excess, the log
    estimator merges, and the result stays finite and close to the truth."""
    import shutil

    import OpenImageIO as oiio

    folder, meta = tiff_bracket
    frames = []
    for k, p in enumerate(frames_of(folder, meta)):
        dst = tmp_path / p.name
        shutil.copy(p, dst)
        if k == 1:
            buf = oiio.ImageBuf(str(dst))
            v = buf.get_pixels(oiio.FLOAT)
            v = np.clip(v, 0, 1) ** 0.8
            buf.set_pixels(buf.roi, v)
            assert buf.write(str(dst), "uint16")
        frames.append(dst)
    out, s = _merge(run, tmp_path, frames, "--crf", "gamma:2.2")
    excess = json.loads(out.with_suffix(".profile.json").read_text())["excess_variance"]
    assert excess["kept"] and max(excess["levels_sd"]) > 0.02, excess
    assert s["estimator"] == "log"
    est, _ = read_exr(out)
    truth, _ = read_exr(folder / "truth.exr")
    assert np.isfinite(est).all() and log_rmse(est, truth) < 0.5


#: read noise before the gain (electrons^2) and after it (code values^2) of the mixed-ISO
#: bracket: sigma_o2 at gain g (ISO / 100) = PRE alpha g^2 + POST, alpha = 0.25 at ISO 100
MIXED_PRE, MIXED_POST, MIXED_ALPHA = 40.0, 9.0, 0.25


def _iso_noise(gain: float) -> dict:
    alpha = MIXED_ALPHA * gain * gain
    return {"sigma_o2": MIXED_PRE * alpha + MIXED_POST, "alpha": alpha}


@pytest.fixture(scope="module")
def mixed_iso_bracket(tmp_path_factory, run):
    """Two ISO 100 frames (0.01 s, 0.16 s) and one ISO 400 frame (0.05 s: exposure 0.2 at
    ISO 100) of one scene (an EXR written here, electrons per second), each run of
    simulate with the noise of its ISO (``_iso_noise``); the DNGs copied into one folder."""
    from hdrmerge_cli.io.images import write_exr

    root = tmp_path_factory.mktemp("mixed_iso")
    rng = np.random.default_rng(11)
    scene = np.exp(rng.uniform(np.log(200.0), np.log(1.5e5), (128, 192)))
    write_exr(str(root / "scene.exr"), np.repeat(scene[..., None], 3, axis=2).astype(np.float32), ["R", "G", "B"], {})
    bracket = root / "bracket"
    bracket.mkdir()
    metas = {}
    for name, times, iso, seed in (("low", "0.01,0.16", 100, 1), ("high", "0.05", 400, 2)):
        p = _iso_noise(iso / 100)
        folder = root / name
        run("simulate", "-o", folder, "-q", "--scene", root / "scene.exr", "--times", times, "--iso", iso,
            "--alpha", p["alpha"], "--sigma-o2", p["sigma_o2"], "--seed", seed)
        metas[name] = json.loads((folder / "simulation.json").read_text())
        for frame in metas[name]["frames"]:
            (bracket / f"{name}_{frame}").write_bytes((folder / frame).read_bytes())
    return root, sorted(bracket.iterdir()), metas["low"]


def _mixed_profile(path, isos):
    """A calibrate-noise style profile: ``noise["ISO100"] = {channel: {sigma_o2, alpha, beta}}``
    (sigma_o2 with the quantisation's 1/12, as calibrate-noise measures it)."""
    from hdrmerge_cli.core.crf import CRF
    from hdrmerge_cli.io.profile import new_profile

    prof = new_profile({"make": "test", "model": "mixed iso"}, 14, CRF("linear"), [], "calibrate-noise")
    for iso in isos:
        p = _iso_noise(iso / 100)
        prof["noise"][f"ISO{iso}"] = {ch: {"sigma_o2": p["sigma_o2"] + 1 / 12, "alpha": p["alpha"], "beta": 0.0}
                                      for ch in ("R", "G", "B")}
    path.write_text(json.dumps(prof))
    return path


def test_mixed_iso_bracket_merges_each_frame_with_its_isos_noise(run, tmp_path, mixed_iso_bracket):
    """A profile with every ISO: each frame is merged with its own ISO's noise (the output
    records it per ISO) and the merge is closer to the truth than one with the first
    frame's noise for every frame (seeded; log RMS error 0.095 against 0.132 when written)."""
    root, frames, low = mixed_iso_bracket
    ref = str(low["reference_exposure"])  # in the ISO 100 frames' seconds, as the merge's h (first frame ISO 100)
    truth = mosaic(read_exr(root / "low" / "truth.exr")[0], low["cfa_pattern"])
    profile = _mixed_profile(tmp_path / "p.json", (100, 400))
    errors = {}
    for name, args in (("per_iso", ("--profile", profile)), ("as_crf", ("--crf", profile)),
                       ("first", ("--noise", "sigma_o2={sigma_o2},alpha={alpha}".format(**_iso_noise(1.0))))):
        out, s = _merge(run, tmp_path, frames, "--cfa", "--reference", ref, *args, name=f"{name}.exr")
        pixels, attrs = read_exr(out)
        assert attrs["hdrmerge:referenceExposure"] == pytest.approx(float(ref), rel=1e-6)
        assert [f["iso"] for f in s["frames"]] == [100, 100, 400]
        errors[name] = log_rmse(pixels[..., 0], truth)
        if name == "first":
            assert "noise_per_iso" not in s
            continue
        assert s["noise"]["R"]["alpha"] == MIXED_ALPHA  # the reference frame's
        assert s["noise_per_iso"]["ISO400"]["G2"]["alpha"] == pytest.approx(16 * MIXED_ALPHA)
        saved = json.loads(out.with_suffix(".profile.json").read_text())
        assert saved["noise"]["noise_per_iso"] == s["noise_per_iso"]
    assert errors["per_iso"] == errors["as_crf"]
    assert errors["per_iso"] < 0.85 * errors["first"]


@pytest.mark.parametrize("isos", [(100, 200), (100,)])
def test_mixed_iso_bracket_with_a_profile_missing_an_iso_fails(run, tmp_path, mixed_iso_bracket, isos):
    _, frames, _ = mixed_iso_bracket
    profile = _mixed_profile(tmp_path / "p.json", isos)
    proc = run("merge", *frames, "-o", tmp_path / "out.exr", "--profile", profile, check=False)
    assert proc.returncode == 1 and not (tmp_path / "out.exr").exists()
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    keys = ", ".join(f"'ISO{i}'" for i in isos)
    assert len(lines) == 1 and "p.json" in lines[0] and "ISO400" in lines[0] and f"has {keys})" in lines[0]


def test_mixed_iso_bracket_measured_without_a_profile_warns(run, tmp_path, mixed_iso_bracket):
    _, frames, _ = mixed_iso_bracket
    proc = run("merge", *frames, "-o", tmp_path / "out.exr")
    assert "differ in ISO" in proc.stderr and "calibrate-noise" in proc.stderr
