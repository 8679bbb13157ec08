"""calibrate-noise end to end: brackets, darks/flats, profile merging, plots, bad input."""
import dataclasses
import json

import pytest

from conftest import SHARED, frames_of, needs_shared
from hdrmerge_cli.core.errors import HdrMergeError


def simulate(run, folder, *args):
    run("simulate", "-o", folder, "-q", *args)
    return json.loads((folder / "simulation.json").read_text())


@pytest.mark.parametrize("seed", [1, 2])
def test_three_frame_bracket_far_apart_uses_its_pairs_and_states_their_precision(run, tmp_path, seed):
    """A still 3-frame DNG bracket of the built-in scene (frames about 270 times apart):
    sigma_o2 and alpha come from the exposure pairs, each within 4 of its reported
    standard errors of the simulation's truth; the profile states those standard errors
    and the Cramer-Rao bound of the bracket's contrasts, which lies below them and not
    far (the fit is near efficient)."""
    meta = simulate(run, tmp_path / "b", "--frames", "3", "--alpha", "16", "--sigma-o2", "16", "--seed", str(seed))
    profile = tmp_path / "n.json"
    run("calibrate-noise", *frames_of(tmp_path / "b", meta), "-o", profile)
    truth = meta["sensor"]
    for ch, e in json.loads(profile.read_text())["noise"]["ISO100"].items():
        assert e["method"]["alpha"] == e["method"]["sigma_o2"] == "exposure pairs"
        assert len(e["exposure_ratios"]) == 2
        se, crb = e["stderr"], e["achievable_stderr"]
        assert abs(e["alpha"] - truth["alpha"]) < 4 * se["alpha"] and se["alpha"] < 0.04 * truth["alpha"]
        assert abs(e["sigma_o2"] - truth["sigma_o2_total"]) < 4 * se["sigma_o2"]
        assert se["sigma_o2"] < 0.02 * truth["sigma_o2_total"]
        for k in ("sigma_o2", "alpha"):
            assert crb[k] <= 1.2 * se[k] and se[k] <= 2 * crb[k]


@pytest.mark.parametrize("seed", [4, 5])
def test_a_dark_bracket_measures_the_gain_near_its_bound(run, tmp_path, seed):
    """A 3-frame 12-bit bracket (1/250, 1/60, 1/15 s; sqrt(alpha) 1, sigma_o 6, black 64)
    of a dark scene around a small bright flame: over 99 % of photosites below 5 % of
    white in every frame, the shortest frame at about 2 codes above black, read noise
    alone.  Every channel's alpha lies within 2 of its stated standard errors of the
    truth, and that error within 1.25 times the Cramer-Rao bound of all the photosites'
    exposure contrasts (the darkest pair's ratio is measured again, weighted by what each
    pixel tells of it, and is not left to read as gain: with the plain ratio, seeds 4 and
    5 give alpha 2.2 and 3.4 for G2, 4.4 and 5.3 standard errors off)."""
    import numpy as np
    import OpenImageIO as oiio
    from scipy import ndimage as ndi

    rng = np.random.default_rng(7)
    tex = np.exp(ndi.gaussian_filter(rng.normal(0, 1, (512, 512)), 3) * 8)
    y, x = np.mgrid[0:512, 0:512]
    r = np.hypot(y - 300, x - 260)
    scene = (tex / np.median(tex) * 200.0 + 8e3 / (1 + (r / 20.0) ** 2) + np.where(r < 6, 2e5, 0.0))
    buf = oiio.ImageBuf(oiio.ImageSpec(512, 512, 3, oiio.FLOAT))
    buf.set_pixels(oiio.ROI(), (scene[..., None] * np.array([0.9, 1.0, 0.7])).astype(np.float32))
    buf.write(str(tmp_path / "scene.exr"))
    meta = simulate(run, tmp_path / "b", "--scene", tmp_path / "scene.exr", "--times", "1/250,1/60,1/15",
                    "--bits", "12", "--black", "64", "--alpha", "1", "--sigma-o2", "36", "--seed", str(seed))
    profile = tmp_path / "n.json"
    run("calibrate-noise", *frames_of(tmp_path / "b", meta), "-o", profile)
    for ch, e in json.loads(profile.read_text())["noise"]["ISO100"].items():
        se, crb = e["stderr"]["alpha"], e["achievable_stderr"]["alpha"]
        assert abs(e["alpha"] - 1.0) <= 2 * se, (ch, e["alpha"], se)
        assert se <= 1.25 * crb, (ch, se, crb)
        assert len(e["exposure_ratios"]) == 2, ch  # both pairs, the darkest too


@pytest.fixture(scope="module")
def calibration_set(tmp_path_factory, run):
    """A 5-frame bracket, 4 darks and flats (2 frames at 6 levels) of one sensor with
    gain FPN (beta = 1e-4)."""
    root = tmp_path_factory.mktemp("calset")
    sensor = ("--alpha", "0.5", "--sigma-o2", "16", "--beta", "1e-4")
    meta = simulate(run, root / "bracket", "--size", "384x256", "--frames", "5", *sensor)
    simulate(run, root / "darks", "--scene", "dark", "--size", "192x192", "--frames", "4", *sensor)
    simulate(run, root / "flats", "--scene", "flat", "--scale", "1000", "--size", "192x192", "--frames", "6",
             "--repeat", "2", *sensor)
    return root, meta


def test_bracket_alone_gives_sigma_o2_and_alpha_from_exposure_pairs(run, tmp_path):
    folder = tmp_path / "cal"
    meta = simulate(run, folder, "--frames", "5")
    s = json.loads(run("calibrate-noise", *frames_of(folder, meta), "-o", tmp_path / "n.json", "--json").stdout)
    sensor = meta["sensor"]
    for ch in ("R", "G", "B", "G2"):
        fit = s["noise"]["ISO100"][ch]
        assert fit["alpha"] == pytest.approx(sensor["alpha"], rel=0.05)
        assert fit["sigma_o2"] == pytest.approx(sensor["sigma_o2_total"], rel=0.1)
        assert fit["model"] == "affine" and fit["method"]["alpha"] == "exposure pairs"
        assert len(fit["exposure_ratios"]) >= 3
    assert [f["limited"] for f in s["frames"]][-1] == "photon"
    first = s["frames"][0]
    assert first["break_point"]["G"]["code_value"] == pytest.approx(
        s["noise"]["ISO100"]["G"]["sigma_o2"] / s["noise"]["ISO100"]["G"]["alpha"] ** 0.5, rel=1e-3)


def test_darks_and_flats_are_the_reference_and_find_gain_fpn(run, tmp_path, calibration_set):
    root, meta = calibration_set
    out = tmp_path / "n.json"
    s = json.loads(run("calibrate-noise", *frames_of(root / "bracket", meta), "--darks", root / "darks",
                       "--flats", root / "flats", "-o", out, "--json").stdout)
    for ch, fit in s["noise"]["ISO100"].items():
        assert fit["method"] == {"sigma_o2": "photon transfer: darks", "alpha": "photon transfer: flats",
                                 "beta": "photon transfer: averaged flats"}
        assert fit["sigma_o2"] == pytest.approx(16 + 1 / 12, rel=0.03)
        assert fit["alpha"] == pytest.approx(0.5, rel=0.03)
        assert fit["model"] == "quadratic" and fit["beta"] == pytest.approx(1e-4, rel=0.15)
        assert fit["from_photographs"]["alpha"] == pytest.approx(0.5, rel=0.05)
    assert json.loads(out.read_text())["noise"] == s["noise"]


def test_flats_alone_are_enough(run, tmp_path, calibration_set):
    root, _ = calibration_set
    s = json.loads(run("calibrate-noise", "--flats", root / "flats", "-o", tmp_path / "n.json", "--json").stdout)
    fit = s["noise"]["ISO100"]["G"]
    assert fit["alpha"] == pytest.approx(0.5, rel=0.03)
    assert fit["method"]["sigma_o2"] == "photon transfer: intercept of the flats"


def test_profile_merges_new_iso_and_keeps_the_rest(run, tmp_path, calibration_set):
    root, meta = calibration_set
    prof = tmp_path / "p.json"
    run("calibrate-noise", *frames_of(root / "bracket", meta), "-o", prof)
    other = simulate(run, tmp_path / "iso400", "--size", "256x192", "--frames", "3", "--iso", "400",
                     "--alpha", "2", "--sigma-o2", "30")
    run("calibrate-noise", *frames_of(tmp_path / "iso400", other), "--profile", prof)  # in place
    noise = json.loads(prof.read_text())["noise"]
    assert set(noise) == {"ISO100", "ISO400"}
    # 3 small frames about 280 times apart: the exposure pairs tell alpha to about 12 %
    g400 = noise["ISO400"]["G"]
    assert g400["method"]["alpha"] == "exposure pairs" and abs(g400["alpha"] - 2.0) < 4 * g400["stderr"]["alpha"]
    assert noise["ISO100"]["G"]["alpha"] == pytest.approx(0.5, rel=0.05)


def test_profile_of_another_camera_is_refused(run, tmp_path, calibration_set):
    root, meta = calibration_set
    prof = tmp_path / "p.json"
    run("calibrate-noise", *frames_of(root / "bracket", meta), "-o", prof)
    data = json.loads(prof.read_text())
    data["camera"]["model"] = "Other X1"
    prof.write_text(json.dumps(data))
    before = prof.read_text()
    proc = run("calibrate-noise", *frames_of(root / "bracket", meta), "--profile", prof, check=False)
    assert proc.returncode == 1 and "Other X1" in proc.stderr and prof.read_text() == before


def test_plot_is_drawn_and_a_bad_type_writes_nothing(run, tmp_path, calibration_set):
    root, meta = calibration_set
    frames = frames_of(root / "bracket", meta)
    run("calibrate-noise", *frames, "--flats", root / "flats", "-o", tmp_path / "n.json", "--plot", tmp_path / "n.png")
    assert (tmp_path / "n.png").read_bytes()[:4] == b"\x89PNG"
    proc = run("calibrate-noise", *frames, "-o", tmp_path / "m.json", "--plot", tmp_path / "n.xyz", check=False)
    assert proc.returncode == 1 and "n.xyz" in proc.stderr and not (tmp_path / "m.json").exists()


@needs_shared
def test_the_real_dng_gives_a_plausible_fit(run, tmp_path):
    s = json.loads(run("calibrate-noise", SHARED / "raw" / "colorchart.dng", "-o", tmp_path / "n.json", "--json").stdout)
    for fit in next(iter(s["noise"].values())).values():
        assert fit["sigma_o2"] > 0 and fit["alpha"] > 0 and fit["beta"] >= 0 and fit["points"] > 10
        assert fit["residual_rms"] < 0.1


# ---------------------------------------------------------------- bad input
def test_jpeg_without_a_crf_is_refused(run, tmp_path, jpeg_bracket):
    folder, meta = jpeg_bracket
    proc = run("calibrate-noise", *frames_of(folder, meta), "-o", tmp_path / "n.json", check=False)
    assert proc.returncode == 1 and "--crf" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "n.json").exists()


def test_all_clipped_frames_are_refused_with_reasons(run, tmp_path):
    meta = simulate(run, tmp_path / "sat", "--size", "64x64", "--times", "1000,2000")
    proc = run("calibrate-noise", *frames_of(tmp_path / "sat", meta), "-o", tmp_path / "n.json", check=False)
    assert proc.returncode == 1 and "no usable frame" in proc.stderr and "clipped" in proc.stderr
    assert not (tmp_path / "n.json").exists()


def test_a_black_frame_is_skipped_with_a_warning(run, tmp_path, calibration_set):
    root, meta = calibration_set
    dark = sorted((root / "darks").glob("*.dng"))[0]
    proc = run("calibrate-noise", dark, *frames_of(root / "bracket", meta), "-o", tmp_path / "n.json")
    assert f"{dark}: skipped, it is black" in proc.stderr


def test_too_few_windows_and_missing_inputs(run, tmp_path, calibration_set):
    root, _ = calibration_set
    meta = simulate(run, tmp_path / "tiny", "--size", "32x32", "--frames", "1")
    proc = run("calibrate-noise", *frames_of(tmp_path / "tiny", meta), "-o", tmp_path / "n.json", check=False)
    assert proc.returncode == 1 and "too few" in proc.stderr
    proc = run("calibrate-noise", "-o", tmp_path / "n.json", check=False)
    assert proc.returncode == 1 and "IMAGES" in proc.stderr
    proc = run("calibrate-noise", "--darks", root / "darks", "-o", tmp_path / "n.json", check=False)
    assert proc.returncode == 1 and "--flats" in proc.stderr
    proc = run("calibrate-noise", "--flats", root / "darks", "-o", tmp_path / "n.json", check=False)
    assert proc.returncode == 1 and "not a flat field" in proc.stderr  # darks as flats: no light
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("no frames here")
    proc = run("calibrate-noise", "--flats", tmp_path / "empty", "-o", tmp_path / "n.json", check=False)
    assert proc.returncode == 1 and "no image or RAW files among the flats" in proc.stderr
    assert not (tmp_path / "n.json").exists()


def test_frames_of_unknown_iso_mixed_with_known_are_refused(calibration_set):
    from hdrmerge_cli.io.frames import read_frame
    from hdrmerge_cli.pipeline.calibrate import _check_group

    root, meta = calibration_set
    frames = [read_frame(p) for p in frames_of(root / "bracket", meta)]
    frames[1] = dataclasses.replace(frames[1], iso=None)
    with pytest.raises(HdrMergeError, match="no ISO"):
        _check_group(frames, "photographs")


def test_merge_without_a_profile_measures_the_noise_on_the_bracket(run, tmp_path, calibration_set):
    root, meta = calibration_set
    out = tmp_path / "m.exr"
    s = json.loads(run("merge", *frames_of(root / "bracket", meta), "-o", out, "--json").stdout)
    assert s["noise_source"].startswith("measured on the bracket") and s["variance"] == "model"
    for ch in ("R", "G", "B", "G2"):
        assert s["noise"][ch]["alpha"] == pytest.approx(0.5, rel=0.05)
        assert s["noise"][ch]["sigma_o2"] == pytest.approx(16 + 1 / 12, rel=0.1)
        assert s["noise"][ch]["beta"] == 0  # a bracket's beta may be texture: recorded, not used
    recorded = json.loads((tmp_path / "m.profile.json").read_text())["noise"]["estimated_from_bracket"]
    assert recorded["G"]["method"]["alpha"] == "exposure pairs" and recorded["G"]["subsample_sites"] > 0
    s = json.loads(run("merge", *frames_of(root / "bracket", meta), "-o", out, "--overwrite", "--variance", "photon",
                       "--estimator", "log", "--json").stdout)
    assert s["noise_source"] is None and s["noise"] is None  # the ML estimator needs the noise model; log does not


def test_linearised_tiff_through_its_crf(run, tmp_path, tiff_bracket):
    """16-bit TIFFs of a 12-bit linear sensor through gamma 2.2: linearised at 16 bits the
    parameters scale by (65535 / 4095)^2."""
    folder, meta = tiff_bracket
    s = json.loads(run("calibrate-noise", *frames_of(folder, meta), "--crf", "gamma:2.2", "-o", tmp_path / "n.json",
                       "--json").stdout)
    k2 = (65535 / 4095) ** 2
    for fit in next(iter(s["noise"].values())).values():
        assert fit["alpha"] == pytest.approx(meta["sensor"]["alpha"] * k2, rel=0.15)
        assert fit["sigma_o2"] == pytest.approx(meta["sensor"]["sigma_o2_total"] * k2, rel=0.3)


def test_merge_falls_back_to_photon_weights_when_the_bracket_shows_no_noise(run, tmp_path):
    meta = simulate(run, tmp_path / "sat", "--size", "64x64", "--times", "1000,2000")
    s = json.loads(run("merge", *frames_of(tmp_path / "sat", meta), "-o", tmp_path / "m.exr", "--json").stdout)
    assert s["noise_source"] is None and s["variance"] == "photon"


@pytest.mark.parametrize("seed", [3, 4])
def test_merge_fast_path_lies_within_its_standard_errors_of_the_truth(run, tmp_path, seed):
    """merge's noise measurement on drawn tiles: within 4 of its reported standard errors of
    the simulation's sigma_o2 and alpha (from the exposure pairs), the standard errors a few
    percent at most and not far above the Cramer-Rao bound of the drawn sites; the
    sites drawn from the codes held as the frames were decoded, so the measurement decodes
    nothing itself."""
    from hdrmerge_cli.io.frames import HeldCodes, load_codes, read_frame
    from hdrmerge_cli.io.metadata import sample_pattern
    from hdrmerge_cli.pipeline.bracket import choose_crf
    from hdrmerge_cli.pipeline.noise import estimate_bracket_noise

    meta = simulate(run, tmp_path / "b", "--frames", "5", "--seed", str(seed), "--alpha", "0.5", "--sigma-o2", "16")
    frames = sorted((read_frame(p) for p in frames_of(tmp_path / "b", meta)), key=lambda f: f.exposure_time)
    crf = choose_crf(frames, None, warn=False)
    held = HeldCodes()
    for f in frames:
        held.hold(f, load_codes(f))

    def no_decode(frame):
        raise AssertionError(f"{frame.path} decoded again")

    held.decode = no_decode
    used, entries, _ = estimate_bracket_noise(frames, crf, held, sample_pattern(frames[0]))
    truth = meta["sensor"]
    for ch in ("R", "G", "B", "G2"):
        se = entries[ch]["stderr"]
        assert entries[ch]["method"]["alpha"] == "exposure pairs"
        assert se["alpha"] < 0.05 * truth["alpha"] and se["sigma_o2"] < 0.03 * truth["sigma_o2_total"]
        assert abs(used[ch]["alpha"] - truth["alpha"]) < 4 * se["alpha"]
        assert abs(used[ch]["sigma_o2"] - truth["sigma_o2_total"]) < 4 * se["sigma_o2"]
        assert entries[ch]["achievable_stderr"]["alpha"] <= 1.2 * se["alpha"]  # the bound, and the fit near it
        assert entries[ch]["achievable_stderr"]["alpha"] >= 0.3 * se["alpha"]


def test_merge_measures_the_other_channels_when_one_is_clipped_everywhere(run, tmp_path):
    """An 8-bit bracket whose blue channel is clipped in every frame, merged with the ML
    estimator (which needs the noise): red and green are measured, blue takes their median
    with a warning, and the merge keeps its noise model (not photon weights for every
    channel)."""
    import OpenImageIO as oiio

    meta = simulate(run, tmp_path / "b", "--format", "tif", "--out-bits", "8", "--crf", "gamma:2.5",
                    "--size", "256x192", "--frames", "4")
    paths = frames_of(tmp_path / "b", meta)
    for p in paths:
        buf = oiio.ImageBuf(str(p))
        pixels = buf.get_pixels(oiio.UINT8)
        pixels[..., 2] = 255
        buf.set_pixels(buf.roi, pixels)
        assert buf.write(str(p))
    res = run("merge", *paths, "-o", tmp_path / "m.exr", "--json", "--estimator", "ml")
    s = json.loads(res.stdout)
    assert "channel B" in res.stderr and "median of channels R, G" in res.stderr
    assert s["noise"]["B"]["alpha"] == pytest.approx(sorted([s["noise"]["R"]["alpha"], s["noise"]["G"]["alpha"]])[0]
                                                     + abs(s["noise"]["R"]["alpha"] - s["noise"]["G"]["alpha"]) / 2)
    profile = json.loads((tmp_path / "m.profile.json").read_text())
    assert profile["noise"]["estimated_from_bracket"]["B"]["stand_in_from"] == ["R", "G"]
