"""Exposures measured on the frames: the estimator against known exposures,
the warning on a mislabelled bracket (and none on a correct one), the order check on a
film-bracket-like case, ``--times estimate`` and ``info --times``."""
from __future__ import annotations

import json

import numpy as np
import pytest

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.exposure_estimate import (
    PairRatio, estimate_exposures, pair_comparagram, response_from_comparagrams, robust_log_ratio,
)
from hdrmerge_cli.core.samples import order_test
from hdrmerge_cli.core.samples import border_mask, constant_border
from tests.conftest import SHARED, frames_of, needs_shared


def _scene(rng, shape=(96, 128)):
    """Textured positive radiance over about 6 stops."""
    y, x = np.mgrid[: shape[0], : shape[1]]
    return np.exp2(6 * x / shape[1] - 6) * (1 + 0.3 * rng.random(shape))


def test_robust_ratio_recovers_known_exposures_with_outliers():
    rng = np.random.default_rng(1)
    e = _scene(rng).ravel()
    for ratio in (1.0, 2.0, 4.0, 8.0):
        a = e * 0.1 * (1 + 0.01 * rng.standard_normal(e.size))
        b = e * 0.1 * ratio * (1 + 0.01 * rng.standard_normal(e.size))
        b[:500] *= 3.0  # motion: 500 pixels off the comparametric line
        ok = (a > 1e-3) & (b < 0.9)
        r = robust_log_ratio(a[ok], b[ok])
        assert r.measured
        assert abs(r.log_ratio - np.log(ratio)) < 0.005, ratio


def test_estimate_names_the_mislabelled_frame_and_keeps_the_reference_label():
    true = np.log(np.array([1 / 120, 1 / 60, 1 / 30, 1 / 15, 1 / 8]))
    label = true.copy()
    label[2] = np.log(1 / 15)  # says 1/15 s for 1/30 s: 1 EV too long
    pairs = [PairRatio(float(d), 1e-3, 0.01, 10_000, 10_000) for d in np.diff(true)]
    est = estimate_exposures(label, pairs)
    assert est.mislabelled() == [2]
    assert est.difference_ev[2] == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(est.log_h, true, atol=1e-9)
    correct = estimate_exposures(true, pairs)
    assert correct.mislabelled() == []


def test_a_run_of_wrong_labels_is_named_not_the_majority():
    true = np.log(np.array([1, 2, 4, 8, 8, 8, 8], float))  # the camera stopped changing after 4th
    label = np.log(np.array([1, 2, 4, 8, 16, 32, 64], float))
    pairs = [PairRatio(float(d), 1e-3, 0.01, 10_000, 10_000) for d in np.diff(true)]
    est = estimate_exposures(label, pairs)
    assert est.mislabelled() == [4, 5, 6]


def test_a_label_is_called_wrong_only_where_its_estimate_is_measured_and_pinned():
    """Frame 2 labelled 1/2 EV long.  Its standard error is the pairs' errors from the
    reference (frame 1) in quadrature; it is called wrong with precise pairs, not where that
    error is 0.2 EV (0.5 < 3 x 0.2), and not where a pair it chains through shares 2 % of the
    frame (not measured; frame 0's estimate does not chain through it)."""
    true = np.log(np.array([1 / 60, 1 / 30, 1 / 15]))
    label = true.copy()
    label[2] += 0.5 * np.log(2)

    def pairs(se, coverage):
        return [PairRatio(float(np.log(2)), se[0], 0.01, 10_000, 10_000, coverage[0]),
                PairRatio(float(np.log(2)), se[1], 0.01, 10_000, 10_000, coverage[1])]

    est = estimate_exposures(label, pairs((1e-3, 2e-3), (0.5, 0.5)))
    assert est.reference == 1 and est.mislabelled() == [2]
    np.testing.assert_allclose(est.stderr_ev(), [1e-3 / np.log(2), 0.0, 2e-3 / np.log(2)])
    vague = estimate_exposures(label, pairs((1e-3, 0.2 * np.log(2)), (0.5, 0.5)))
    assert vague.stderr_ev()[2] == pytest.approx(0.2) and vague.mislabelled() == []
    narrow = estimate_exposures(label, pairs((1e-3, 2e-3), (0.5, 0.02)))
    assert narrow.measured().tolist() == [True, True, False] and narrow.mislabelled() == []
    assert narrow.share().tolist() == [0.5, 1.0, 0.02]


def test_unmeasured_pairs_keep_their_labels():
    label = np.log(np.array([1, 2, 4], float))
    pairs = [PairRatio(float("nan"), np.inf, np.nan, 10, 0), PairRatio(np.log(2), 1e-3, 0.01, 10_000, 10_000)]
    est = estimate_exposures(label, pairs)
    assert est.mislabelled() == []


def test_response_from_comparagrams_recovers_a_gamma_curve():
    rng = np.random.default_rng(2)
    e = _scene(rng, (128, 128)).ravel()
    t = np.array([1, 2, 4, 8], float) / 8
    codes = [np.clip(np.rint(255 * np.clip(e * tj * 2, 0, 1) ** (1 / 2.2)), 0, 255).astype(np.int64) for tj in t]
    grams = [pair_comparagram(codes[k - 1], codes[k], 256) for k in range(1, 4)]
    g = response_from_comparagrams(grams, np.diff(np.log(t)))
    z = np.arange(60, 240)
    want = 2.2 * np.log(z / 255.0)
    got = g[z] - g[255 - 15] + want[-1 - 15 + 15] if False else g[z] - g[200] + 2.2 * np.log(200 / 255.0)
    assert np.max(np.abs(got - want)) < 0.08


def test_constant_borders_are_found_and_noise_floor_frames_pass_the_order_check():
    """The 16-frame film bracket's case: blue scan borders constant in every frame, the
    darkest frames at the noise floor (their mean code order is noise)."""
    rng = np.random.default_rng(3)
    e = _scene(rng, (80, 100))
    frames = []
    for t in (1 / 64, 1 / 32, 1 / 4, 1):
        z = np.clip(18 + 230 * np.clip(e * t, 0, 1) ** (1 / 2.2) + rng.normal(0, 1.5, e.shape), 0, 255)
        img = np.repeat(np.rint(z)[..., None], 3, axis=-1).astype(np.uint8)
        img[:6], img[-6:], img[:, :9], img[:, -9:] = (40, 60, 200), (40, 60, 200), (40, 60, 200), (40, 60, 200)
        frames.append(img)
    assert constant_border(frames, 8) == (6, 6, 9, 9)
    inside = border_mask(frames[0].shape, constant_border(frames, 8))[..., None]
    for a, b in zip(frames, frames[1:]):
        usable = (a < 255) & (b < 255) & inside
        assert not order_test(a, b, usable, 1.5).disordered
    # genuinely disordered frames (labels swapped) still fail
    usable = (frames[3] < 255) & (frames[2] < 255) & inside
    assert order_test(frames[3], frames[2], usable, 1.5).disordered


# ---------------------------------------------------------------- end to end
def _times_arg(meta, k=None, factor=1.0):
    t = list(meta["exposure_times"])
    if k is not None:
        t[k] *= factor
    return ",".join(repr(x) for x in t)


def test_merge_warns_about_a_mislabelled_dng_frame(run, dng_bracket, tmp_path):
    folder, meta = dng_bracket
    files = frames_of(folder, meta)
    ok = run("merge", *files, "-o", tmp_path / "ok.exr", "--json")
    assert "labelled" not in ok.stderr
    check = json.loads(ok.stdout)["exposure_check"]
    assert not any(f["mislabelled"] for f in check["frames"])
    bad = run("merge", *files, "-o", tmp_path / "bad.exr", "--times", _times_arg(meta, 2, 2.0), "--json")
    name = files[2].name
    lines = [ln for ln in bad.stderr.splitlines() if "labelled" in ln]
    assert len(lines) == 1 and name in lines[0] and "--times estimate" in lines[0], bad.stderr
    check = json.loads(bad.stdout)["exposure_check"]
    row = next(f for f in check["frames"] if f["name"] == name)
    assert row["mislabelled"] and row["difference_ev"] == pytest.approx(1.0, abs=0.1)
    assert row["estimate_seconds"] == pytest.approx(meta["exposure_times"][2], rel=0.05)


def test_times_estimate_merges_as_with_the_true_labels(run, dng_bracket, tmp_path):
    from hdrmerge_cli.io.images import read_exr

    folder, meta = dng_bracket
    files = frames_of(folder, meta)
    (tmp_path / "times.txt").write_text("".join(
        f"{f.name} {t!r}\n" for f, t in zip(files, [x * (2.0 if k == 2 else 1.0)
                                                    for k, x in enumerate(meta["exposure_times"])])))
    run("merge", *files, "-o", tmp_path / "true.exr", "--reference", "shortest", "-q")
    out = run("merge", *files, "-o", tmp_path / "est.exr", "--reference", "shortest", "--times", "estimate",
              "--times-file", tmp_path / "times.txt", "--json")
    assert json.loads(out.stdout)["exposure_check"]["used"] == "estimates"
    truth = read_exr(folder / "truth.exr")[0][..., :3].astype(np.float64)

    def log_psnr(path):  # log E against the truth after one global scale, over measured pixels
        est = read_exr(path)[0][..., :3].astype(np.float64)
        ok = (truth > 1e-4) & (est > 0) & np.isfinite(est)
        d = np.log(est[ok]) - np.log(truth[ok])
        d -= np.median(d)
        return 20 * np.log10(np.ptp(np.log(truth[ok])) / np.sqrt(np.mean(d * d)))

    # the target: within 0.3 dB of the merge with the true labels (a 1 EV label error)
    assert abs(log_psnr(tmp_path / "est.exr") - log_psnr(tmp_path / "true.exr")) < 0.3


def test_disordered_frames_fail_with_one_line(run, dng_bracket, tmp_path):
    folder, meta = dng_bracket
    files = frames_of(folder, meta)
    t = list(meta["exposure_times"])
    t[1], t[3] = t[3], t[1]  # labels of two frames swapped
    proc = run("merge", *files, "-o", tmp_path / "x.exr", "--times", ",".join(map(repr, t)), check=False)
    assert proc.returncode == 1
    err = proc.stderr.strip().splitlines()
    assert len(err) == 1 and "darker than" in err[0] and "Traceback" not in proc.stderr


def test_info_takes_times_and_reports_estimates(run, dng_bracket):
    folder, meta = dng_bracket
    files = frames_of(folder, meta)
    out = run("info", *files, "--json", "--times", _times_arg(meta, 2, 2.0))
    summary = json.loads(out.stdout)
    est = summary["exposure_estimates"]
    assert [f["mislabelled"] for f in est["frames"]] == [False, False, True, False, False]
    assert files[2].name in out.stderr
    assert all("estimated_exposure_time" in r for r in summary["frames"])
    text = run("info", *files, "--times", _times_arg(meta)).stdout
    assert "estimate" in text.splitlines()[0]
    bad = run("info", *files, "--times", "1/100,1/10", check=False)
    assert bad.returncode == 1 and len(bad.stderr.strip().splitlines()) == 1


@needs_shared
@pytest.mark.parametrize("name", ["office_jpg", "eos5d3_foyer_jpg", "em1ii_kitchen_jpg", "eos70d_kitchen_jpg",
                                  "ex2f_trees_jpg", "stack_jpg", "stack_ghost_jpg", "eos350d_lamps_night_jpg"])
def test_no_false_alarm_on_real_brackets(name):
    from hdrmerge_cli.core.exposure_estimate import estimate_with_response
    from hdrmerge_cli.pipeline import exposure_check as ex
    from hdrmerge_cli.pipeline.bracket import read_bracket
    from hdrmerge_cli.io.metadata import exposure_values

    folder = SHARED / "brackets" / name
    frames = read_bracket(sorted(str(p) for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".png")))
    h = exposure_values(frames)
    s = ex.ordered_samples(frames, h, max_samples=1 << 17)
    est, _ = estimate_with_response(h, s, CRF("srgb", assumed=True))  # no response given
    assert est.mislabelled() == [], est.difference_ev


# ---------------------------------------------------------------- frames that moved (hand-held, no --align)
def _crops(src, dst, meta, step_xy, size=(448, 320)):
    """The simulated frames cropped to ``size``, frame k at offset k * step_xy (a camera
    moving between exposures), written as JPEG with the source's metadata (EXIF times)."""
    import OpenImageIO as oiio

    dst.mkdir()
    w, h = size
    out = []
    for k, name in enumerate(meta["frames"]):
        buf = oiio.ImageBuf(str(src / name))
        x0, y0 = k * step_xy[0], k * step_xy[1]
        crop = np.ascontiguousarray(buf.get_pixels(oiio.UINT8)[y0:y0 + h, x0:x0 + w])
        spec = oiio.ImageSpec(w, h, crop.shape[-1], oiio.UINT8)
        for a in buf.spec().extra_attribs:
            spec.attribute(a.name, a.type, a.value)
        img = oiio.ImageBuf(spec)
        img.set_pixels(oiio.ROI(), crop)
        assert img.write(str(dst / name)), img.geterror()
        out.append(dst / name)
    return out


@pytest.fixture(scope="module")
def moving_bracket(tmp_path_factory, run):
    """4 sRGB JPEG frames 2 EV apart, 448 x 320: ``still`` (the same window of the scene)
    and ``moved`` (each frame 10 px right and 5 px down of the one before: 11.2 px)."""
    folder = tmp_path_factory.mktemp("moving")
    run("simulate", "-o", folder / "src", "-q", "--size", "480x352", "--times", "0.0025,0.01,0.04,0.16",
        "--format", "jpg", "--seed", "5")
    meta = json.loads((folder / "src" / "simulation.json").read_text())
    src = folder / "src"
    return _crops(src, folder / "still", meta, (0, 0)), _crops(src, folder / "moved", meta, (10, 5)), meta


def test_moved_threshold_and_displacement_on_samples():
    from hdrmerge_cli.core.registration import log_irradiance
    from hdrmerge_cli.core.registration import pair_displacement
    from hdrmerge_cli.core.registration import MOVED_PITCHES, moved_threshold_px

    assert moved_threshold_px(1) == 1.5 and moved_threshold_px(0.5) == 1.0
    assert moved_threshold_px(6) == pytest.approx(6 * MOVED_PITCHES)
    rng = np.random.default_rng(4)
    e = _scene(rng, (200, 260))
    e *= 1 + 0.5 * (np.add.outer(np.arange(200) // 9, np.arange(260) // 11) % 2)  # edges to register
    a = log_irradiance(e[20:180, 20:240] * 0.5, 0.5, 2e-3, 0.9)
    b = log_irradiance(e[26:186, 12:232] * 2.0, 2.0, 2e-3, 0.9)  # the camera moved by (-8, +6)
    assert pair_displacement(a, b) == pytest.approx(10.0, abs=0.3)
    assert pair_displacement(a, log_irradiance(e[20:180, 20:240] * 2.0, 2.0, 2e-3, 0.9)) < 0.1
    flat = np.zeros((160, 220), np.float32)
    assert pair_displacement(flat, flat) is None  # nothing to register


def _srgb_table(folder):
    """The simulated frames' own response (sRGB) as a measured CSV table, which the label
    check trusts."""
    v = np.arange(256) / 255
    table = folder / "srgb.csv"
    linear = np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
    table.write_text("".join(f"{z},{float(x)!r}\n" for z, x in enumerate(linear)))
    return table


def test_frames_that_moved_are_reported_instead_of_a_wrong_label(run, moving_bracket, tmp_path):
    """Through the frames' own response given as a measured table (trusted: a model such as
    ``--crf srgb`` is only checked where the bracket's fitted response agrees), a pair that
    moved reads a ratio off its labels: the message names the motion, not a label."""
    _, moved, _ = moving_bracket
    out = run("merge", *moved, "-o", tmp_path / "m.exr", "--crf", _srgb_table(tmp_path), "--align", "off", "--json")
    assert "labelled" not in out.stderr, out.stderr  # without the check: frame_00 "labelled 1/400 s, but ..."
    lines = [ln for ln in out.stderr.splitlines() if "moved between exposures" in ln]
    assert len(lines) == 1 and "cannot be checked" in lines[0] and "--align auto" in lines[0], out.stderr
    check = json.loads(out.stdout)["exposure_check"]
    assert not any(f["mislabelled"] for f in check["frames"]) and any(f["moved"] for f in check["frames"])
    measured = [p["moved_px"] for p in check["pairs"] if p["moved_px"] is not None]
    assert measured and all(9.5 < d < 13 for d in measured), check["pairs"]  # 11.2 px
    assert check["moved_threshold_px"] == 1.5  # samples of every pixel
    # aligned first (the default, --align auto): the tee sees aligned frames, nothing moved
    aligned = run("merge", *moved, "-o", tmp_path / "a.exr", "--crf", "srgb", "--json")
    assert "moved between exposures" not in aligned.stderr and "labelled" not in aligned.stderr, aligned.stderr


def test_a_wrong_label_on_still_frames_is_still_called_wrong(run, moving_bracket, tmp_path):
    still, _, meta = moving_bracket
    times = list(meta["exposure_times"])
    times[1] *= 2.0  # 1 EV too long
    out = run("merge", *still, "-o", tmp_path / "s.exr", "--crf", "srgb", "--times", ",".join(map(repr, times)),
              "--json")
    lines = [ln for ln in out.stderr.splitlines() if "labelled" in ln]
    assert len(lines) == 1 and still[1].name in lines[0], out.stderr
    assert "moved between exposures" not in out.stderr
    check = json.loads(out.stdout)["exposure_check"]
    assert [f["mislabelled"] for f in check["frames"]] == [False, True, False, False]
    registered = [p["moved_px"] for p in check["pairs"] if p["moved_px"] is not None]
    assert registered and max(registered) < 0.5, check["pairs"]


def _exposure_log(name, crf, caplog, times_file=None):
    import logging

    from hdrmerge_cli.pipeline import exposure_check as ex
    from hdrmerge_cli.pipeline.bracket import read_bracket
    from hdrmerge_cli.io.metadata import exposure_values

    folder = SHARED / "brackets" / name
    frames = read_bracket(sorted(str(p) for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".png")),
                          times_file=times_file)
    logger = logging.getLogger("hdrmerge_cli")
    own = not logger.propagate  # the CLI, run in this process, stops it propagating: caplog's handler on it
    caplog.clear()
    if own:
        logger.addHandler(caplog.handler)
    try:
        with caplog.at_level(logging.WARNING, logger="hdrmerge_cli"):
            h = exposure_values(frames)
            rep = ex.resolve_exposures(frames, h, crf, samples=ex.ordered_samples(frames, h)).report
    finally:
        if own:
            logger.removeHandler(caplog.handler)
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING], rep


@needs_shared
@pytest.mark.parametrize("assumed", [True, False])
def test_real_hand_held_bracket_reports_motion_not_a_label(caplog, assumed):
    lines, rep = _exposure_log("stack_handheld_jpg", CRF("srgb", assumed=assumed), caplog)
    assert not any("labelled" in ln for ln in lines), lines
    moved = [ln for ln in lines if "moved between exposures" in ln]
    assert len(moved) == 1 and "IMG_4211.jpg: " in moved[0] and "--align auto" in moved[0], lines
    assert max(p["moved_px"] or 0 for p in rep["pairs"]) > 20  # about 26 px at full resolution


@needs_shared
@pytest.mark.parametrize("name", ["stack_jpg", "office_jpg"])
@pytest.mark.parametrize("assumed", [True, False])
def test_real_still_brackets_get_no_motion_message(caplog, name, assumed):
    times = SHARED / "brackets" / name / "exposure_times_seconds.txt"
    lines, rep = _exposure_log(name, CRF("srgb", assumed=assumed), caplog, str(times) if times.exists() else None)
    assert not any("moved" in ln for ln in lines), lines
    assert not any(f["moved"] for f in rep["frames"])


def test_info_reports_motion_not_a_label(run, moving_bracket, tmp_path):
    """info runs merge's check: a hand-held bracket's frames moved, its labels are right."""
    _, moved, _ = moving_bracket
    out = run("info", *moved, "--crf", _srgb_table(tmp_path), "--json")
    assert "labelled" not in out.stderr, out.stderr
    lines = [ln for ln in out.stderr.splitlines() if "moved between exposures" in ln]
    assert len(lines) == 1 and "cannot be checked" in lines[0], out.stderr
    check = json.loads(out.stdout)["exposure_estimates"]
    assert any(f["moved"] for f in check["frames"]) and not any(f["mislabelled"] for f in check["frames"])


def test_estimate_crf_calls_no_label_of_a_moved_bracket_wrong(run, moving_bracket, tmp_path):
    _, moved, _ = moving_bracket
    out = run("estimate-crf", *moved, "-o", tmp_path / "crf.json")
    assert "labelled" not in out.stderr, out.stderr


def test_ratio_trend_is_zero_for_a_label_and_the_bend_for_a_response():
    """A wrong label moves every log ratio alike: no trend.  Ratios read through a response
    of the wrong power (gamma 2.2 data read as 1.8) change linearly with log brightness:
    the trend is that slope times the 5th-95th percentile span of log y."""
    from hdrmerge_cli.core.exposure_estimate import ratio_trend, robust_log_ratio

    rng = np.random.default_rng(0)
    y = np.exp(rng.uniform(np.log(1e-3), 0.0, 100000))
    w = np.ones_like(y)
    assert ratio_trend(y, np.full(y.size, np.log(2.0)) + rng.normal(0, 0.01, y.size), w) == pytest.approx(0, abs=0.01)
    d = 0.3 * np.log(y) + np.log(2.0)
    span = np.diff(np.percentile(np.log(y), [5, 95]))[0]
    assert ratio_trend(y, d, w) == pytest.approx(0.3 * span, rel=1e-6)
    r = robust_log_ratio(y, 2.0 * y)
    assert abs(r.trend) < 1e-9 and r.log_ratio == pytest.approx(np.log(2.0))


def test_a_wrong_power_is_told_from_a_wrong_label():
    """Differences proportional to the distance in exposure from the reference are one
    slope (a response of the wrong power); one wrong label leaves half its error off it."""
    from hdrmerge_cli.core.exposure_estimate import ExposureEstimate, power_explains

    log_h = np.log(2.0) * np.arange(5.0) * 1.5
    power = ExposureEstimate(log_h, 0.2 * (np.arange(5.0) - 2) * 1.5, [], 2, 1.0)
    label = ExposureEstimate(log_h, np.array([0.0, 0.0, 0.0, 0.0, 1.0]), [], 2, 1.0)
    assert power_explains(power) and not power_explains(label)


@pytest.mark.parametrize("raw", [False, True])
def test_samples_registered_by_the_alignment_warps_line_up(raw):
    """``Samples.registered``: samples of a frame shifted by a known full-resolution
    translation, brought back by that warp, equal the reference's samples (bilinear, off
    the uncovered edge) to within the interpolation of a smooth field; RAW samples are
    moved as whole CFA cells."""
    from hdrmerge_cli.core.samples import Samples

    yy, xx = np.mgrid[0:96, 0:128].astype(np.float32)
    field = lambda dy, dx: (0.5 + 0.3 * np.sin((xx + dx) / 9.0) * np.cos((yy + dy) / 7.0))[..., None]
    step = 2
    pick = (lambda a: a[[i for i in range(a.shape[0]) if (i // 2) % step == 0]][:, [j for j in range(a.shape[1])
                                                                                     if (j // 2) % step == 0]]
            ) if raw else (lambda a: a[::step, ::step])
    ref, moved = pick(field(0, 0)), pick(field(6, -8))  # the frame's pixel (x, y) saw the scene at (x - 8, y + 6)
    s = Samples([ref, moved], np.ones(ref.shape[:2], bool), (0, 0, 0, 0), step, 1 / 4095, raw)
    warp = np.array([[1.0, 0.0, 8.0], [0.0, 1.0, -6.0]])  # reference pixel -> the frame's pixel
    r = s.registered([np.eye(2, 3), warp])
    assert r.v[0] is ref and 0.5 < r.inside.mean() < 0.95
    err = np.abs(r.v[1] - ref)[r.inside]
    assert err.max() < 0.02, err.max()


def test_label_motion_comes_from_the_alignment():
    """``warp_motion``: applied warps leave no displacement between registered frames and
    none is known for a frame left unaligned; warps not applied give the distance between
    where the pair's warps take a corner (of a 100 x 200 frame, samples 2 px apart)."""
    from hdrmerge_cli.core.registration import warp_motion

    warps = [np.array([[1.0, 0, 0.1], [0, 1, 0]]), np.eye(2, 3), np.array([[1.0, 0, 0], [0, 1, -0.2]])]
    m = warp_motion(warps, [True, True, False], True, 100, 200, 2)
    assert m.px == {0: 0.0, 1: None} and m.threshold_px == 3.0
    m = warp_motion(warps[::-1], [False, True, True], True, 100, 200, 2)
    assert m.px == {0: None, 1: 0.0}
    m = warp_motion(warps, [True] * 3, False, 100, 200, 2)
    assert m.px[0] == pytest.approx(0.1) and m.px[1] == pytest.approx(0.2) and not m.moved


def test_normalised_samples_against_direct_levels():
    """core.samples.normalised_samples: an image's codes minus black over the range
    per channel, every step-th row and column; a mosaic's in whole 2 x 2 cells, each site
    with its own colour's levels (independent loop over the sites)."""
    from hdrmerge_cli.core.samples import normalised_samples

    rng = np.random.default_rng(2)
    image = rng.integers(0, 256, (9, 11, 3)).astype(np.uint8)
    v = normalised_samples(image, [0, 1, 2], [255, 250, 245], 3)
    np.testing.assert_allclose(v, (image[::3, ::3] - np.array([0, 1, 2])) / np.array([255, 249, 243]), rtol=1e-6)
    mosaic = rng.integers(0, 4096, (10, 12)).astype(np.uint16)
    cell = np.array([[0, 1], [3, 2]])
    black, white = np.array([10.0, 20.0, 30.0, 40.0]), np.array([4000.0, 4010.0, 4020.0, 4030.0])
    v = normalised_samples(mosaic, black, white, 2, cell)
    rows = [i for i in range(10) if (i // 2) % 2 == 0]
    cols = [j for j in range(12) if (j // 2) % 2 == 0]
    assert v.shape == (len(rows), len(cols), 1)
    for a, i in enumerate(rows):
        for b, j in enumerate(cols):
            k = cell[i % 2, j % 2]
            assert v[a, b, 0] == pytest.approx((mosaic[i, j] - black[k]) / (white[k] - black[k]), rel=1e-6)


def test_linearise_through_a_code_table_equals_the_inverse_response():
    """core.exposure_estimate.linearise: through its table over whole codes, g(v) to float32 precision of
    the direct evaluation; a linear response returns v clipped to [0, 1]."""
    from hdrmerge_cli.core.exposure_estimate import linearise

    crf = CRF("gamma", 2.2)
    v = np.random.default_rng(4).integers(0, 256, (20, 3)) / 255.0
    np.testing.assert_allclose(linearise(v, crf, 1 / 255), np.stack([crf.inverse(v[:, c], c) for c in range(3)], -1),
                               rtol=1e-6, atol=1e-9)
    np.testing.assert_array_equal(linearise(np.array([[-0.1, 0.5, 1.2]]), CRF("linear"), 1 / 255), [[0.0, 0.5, 1.0]])


def test_the_codes_table_is_the_inverse_response_at_each_stored_code_built_once():
    """CRF.codes_table: row c is gamma^-1 of (r - black_c) / (white_c - black_c), clipped to
    [0, 1], written out here by hand for a measured two-channel table and for sRGB (IEC
    61966-2-1); CRF.linear reads whole codes through it; one grid's table is built once."""
    from hdrmerge_cli.core.crf import table_crf

    tab = np.array([[0.0, 0.1, 0.3, 0.6, 1.0], [0.0, 0.2, 0.4, 0.7, 1.0]])
    crf = table_crf(tab)
    got = crf.codes_table(6, black=[1.0, 0.0], white=[5.0, 4.0])
    # channel 0: codes 0..5 -> v = (r - 1) / 4 = -0.25 (clipped to 0), 0, .25, .5, .75, 1 -> the table's entries
    np.testing.assert_allclose(got[0], [0.0, 0.0, 0.1, 0.3, 0.6, 1.0], atol=1e-15)
    np.testing.assert_allclose(got[1], [0.0, 0.2, 0.4, 0.7, 1.0, 1.0], atol=1e-15)
    assert crf.codes_table(6, black=[1.0, 0.0], white=[5.0, 4.0]) is got
    r = np.arange(256) / 255.0
    srgb = np.where(r <= 0.04045, r / 12.92, ((r + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(CRF("srgb").codes_table(256)[0], srgb, rtol=1e-12)
    codes = np.random.default_rng(5).integers(0, 256, (7, 9, 3)).astype(np.uint8)
    np.testing.assert_allclose(CRF("srgb").linear(codes, 256), srgb[codes], rtol=1e-12)


# ---------------------------------------------------------------- the floor: no evidence
def _samples(frames_v):
    """A Samples of ``(H, W, 1)`` float32 frames (every sample off the borders, 8-bit)."""
    from hdrmerge_cli.core.samples import Samples

    v = [np.asarray(f, np.float32)[..., None] for f in frames_v]
    return Samples(v, np.ones(v[0].shape[:2], bool), (0, 0, 0, 0), 1, 1 / 255)


def test_the_floor_is_what_a_frame_reads_where_the_light_is_least_not_its_dust():
    """A film scan's fog reads 13 codes, dust specks (2 % of the pixels, every frame) 0: the
    short frame's floor is the fog (+3 % margin), not the specks' 0, so its fog pixels are
    no evidence; the longer frame's floor (no longer neighbour) is its own 0.5th percentile."""
    rng = np.random.default_rng(3)
    light = rng.uniform(0, 1, (120, 160))
    fog = 13 / 255
    short = np.maximum(fog, 0.2 * light) + rng.normal(0, 0.5 / 255, light.shape)
    long = np.minimum(1, np.maximum(fog, 0.8 * light))
    dust = rng.random(light.shape) < 0.02
    short[dust] = long[dust] = 0
    floors = _samples([short, long]).floors
    assert floors[0][0] == pytest.approx(fog + 0.03, abs=2 / 255)
    assert floors[1][0] == pytest.approx(0.03, abs=1e-6)


def test_frames_that_read_black_are_named_not_refused(run, tmp_path):
    """A phone-like 10-frame bracket, 1/4000 s to 8 s, whose four shortest frames read black
    and each darker than the one before (benchmarks.decisions.black_frames_bracket; the
    noise at the floor sets the order check's margin): it merges with its labels, one
    warning names the black frames, and no label is blamed (the order check does not
    refuse it as 'darker than ... though labelled a longer exposure')."""
    import cv2

    from benchmarks.decisions import black_frames_bracket

    paths, times = black_frames_bracket(tmp_path)
    assert np.mean(cv2.imread(str(paths[2]))) < np.mean(cv2.imread(str(paths[1])))  # darker, labelled longer
    proc = run("merge", *paths, "--times", ",".join(repr(t) for t in times), "-o", tmp_path / "m.exr", "--json",
               check=False)
    assert proc.returncode == 0, proc.stderr
    warnings = [ln for ln in proc.stderr.splitlines() if "warning" in ln]
    assert len(warnings) == 1 and "nothing but black" in warnings[0], proc.stderr
    assert "f2.jpg" in warnings[0] and "f3.jpg" in warnings[0] and "f9.jpg" not in warnings[0]
    frames = json.loads(proc.stdout)["exposure_check"]["frames"]
    assert not any(f["mislabelled"] for f in frames)


@needs_shared
@pytest.mark.parametrize("crf", [None, "srgb"])
@pytest.mark.parametrize("brightest", [16, 13])
def test_the_film_scans_correct_labels_are_not_blamed(run, tmp_path, crf, brightest):
    """Debevec and Malik's Memorial Church scan (correct published times; its darkest frames
    mostly read the film's fog): no label is blamed, with the response measured or sRGB
    given, on all 16 frames and on the 13 brightest: the darkest frames' readings of the
    fog are no evidence."""
    folder = SHARED / "brackets" / "memorial_film_scan_png"
    paths = sorted(folder.glob("*.png"))[:brightest]  # memorial0061 (32 s) onwards
    proc = run("merge", *paths, "--times-file", folder / "exposure_times_seconds.txt", "-o", tmp_path / "m.exr",
               "--json", "--align", "off", *(["--crf", crf] if crf else []))
    assert not any(f["mislabelled"] for f in json.loads(proc.stdout)["exposure_check"]["frames"]), proc.stderr
    assert "labelled" not in proc.stderr and "from the time" not in proc.stderr, proc.stderr


def test_a_ratios_standard_error_counts_the_tiles_not_the_pixels():
    """Per-pixel log ratios sharing an error per tile (a response's misfit, processing): the
    reported standard error matches the spread of the ratio over repeated draws (within
    15 %, 200 draws, seeded), where the independent-pixel one is ten times too small.  The
    independent computation: the standard deviation of the estimate over the draws."""
    rng = np.random.default_rng(11)
    tiles = np.repeat(np.arange(64), 500)
    estimates, errors, naive = [], [], []
    for _ in range(200):
        d = 0.7 + rng.normal(0, 0.05, 64)[tiles] + rng.normal(0, 0.1, tiles.size)
        a = np.full(tiles.size, 0.2)
        r = robust_log_ratio(a, a * np.exp(d), k=10.0, tiles=tiles)
        estimates.append(r.log_ratio)
        errors.append(r.stderr)
        naive.append(robust_log_ratio(a, a * np.exp(d), k=10.0).stderr)
    spread = float(np.std(estimates))
    assert np.mean(errors) == pytest.approx(spread, rel=0.15)
    assert np.mean(naive) < spread / 5


@needs_shared
def test_the_json_blames_what_the_messages_blame(run, tmp_path):
    """One judgement per frame (label_verdicts) for the warnings and --json: on a real
    bracket whose long frames' ratios differ from their correct labels as a response of the
    wrong power makes (eos70d_kitchen_jpg, EXIF times), no warning, no frame mislabelled in
    --json, and those frames carry the reason the response is blamed instead."""
    folder = SHARED / "brackets" / "eos70d_kitchen_jpg"
    proc = run("merge", *sorted(folder.glob("*.jpg")), "-o", tmp_path / "m.exr", "--json", "--no-cache")
    frames = json.loads(proc.stdout)["exposure_check"]["frames"]
    assert "warning" not in proc.stderr, proc.stderr
    assert not any(f["mislabelled"] for f in frames)
    assert [f["name"] for f in frames if f["response_at_fault"]] == ["9.jpg", "10.jpg"]
