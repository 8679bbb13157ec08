"""One pass: each input file is decoded once per merge (default options), whatever the
passes that read it (samples, response, registration, labels, noise, ghosts, the merge and
its re-weighting); each stage of the runner is called at most once, in reading order; and a
frame's stage results follow the frame, not its position."""
from __future__ import annotations

import collections
import threading

import cv2
import numpy as np
import pytest

from tests.conftest import frames_of


@pytest.fixture
def decodes(monkeypatch):
    """Counts per path: LibRaw opens (each followed by an unpack) and OpenImageIO pixel
    reads, however the code reaches them."""
    import rawpy

    import hdrmerge_cli.io.frames as frames_module

    counts: collections.Counter = collections.Counter()
    lock = threading.Lock()

    class Counting(rawpy.RawPy):
        def open_file(self, path):
            with lock:
                counts[str(path)] += 1
            return super().open_file(path)

    read_channels = frames_module._read_channels

    def counting_read(frame, begin, end):
        with lock:
            counts[frame.path] += 1
        return read_channels(frame, begin, end)

    monkeypatch.setattr(rawpy, "RawPy", Counting)
    monkeypatch.setattr(frames_module, "_read_channels", counting_read)
    return counts


def _shifted_dngs(folder, shifts, times=(0.5, 1.0, 2.0), labels=None, seed=1, h=256, w=320):
    """14-bit RGGB DNGs of one textured scene, frame k seeing it ``shifts[k]`` px further right
    (photon and read noise); ``labels``: the exposure times written in the files (default
    ``times``)."""
    from hdrmerge_cli.io.dng_integer import write_dng

    rng = np.random.default_rng(seed)
    e = np.exp(cv2.GaussianBlur(rng.standard_normal((h, w)), (0, 0), 2.0) * 6.0) * np.linspace(0.3, 1.0, w)[None]
    e /= np.percentile(e, 99)
    paths = []
    for k, (t, dx) in enumerate(zip(times, shifts)):
        m = np.float32([[1, 0, dx], [0, 1, 0]])
        s = cv2.warpAffine(e.astype(np.float32), m, (w, h), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_REFLECT) if dx else e
        y = rng.poisson(np.maximum(s * t, 0) * 4000.0) + rng.normal(0, 3, s.shape) + 512
        path = folder / f"f{k}.dng"
        write_dng(str(path), np.clip(np.rint(y), 0, 16383).astype(np.uint16), pattern="RGGB", black=512,
                  white=16383, exposure_time=(labels or times)[k], iso=100, aperture=8.0)
        paths.append(str(path))
    return paths


#: the runner's stages and the choices made on them (hdrmerge_cli.pipeline.run's names), in
#: the order a merge calls them
STAGES = ("read", "ordered_samples", "measure_response", "estimate_alignment", "choose_alignment", "resolve_exposures",
          "bracket_noise", "measure_excess", "choose_models", "find_ghosts", "choose_deghost", "reconstruct")


@pytest.fixture
def stage_calls(monkeypatch):
    """The runner's stage calls, in order: each stage function, as the runner calls it,
    wrapped to record its name."""
    import hdrmerge_cli.pipeline.run as run_module

    calls: list[str] = []
    for name in STAGES:
        fn = getattr(run_module, name)

        def counted(*args, _fn=fn, _name=name, **kwargs):
            calls.append(_name)
            return _fn(*args, **kwargs)

        monkeypatch.setattr(run_module, name, counted)
    return calls


@pytest.fixture
def linearisations(monkeypatch):
    """Every evaluation of a response's inverse during the test: ``(id of the response,
    number of values, made by CRF.codes_table)``, and each table ``codes_table`` built."""
    from hdrmerge_cli.core.crf import CRF

    inverse, table = CRF.inverse, CRF.codes_table
    calls, built, alive, building = [], [], [], threading.local()

    def counted_inverse(self, v, channel=0):
        calls.append((id(self), np.size(v), getattr(building, "on", False)))
        return inverse(self, v, channel)

    def counted_table(self, n_codes, black=0.0, white=None):
        before = len(self._tables)
        building.on = True
        try:
            out = table(self, n_codes, black, white)
        finally:
            building.on = False
        if len(self._tables) > before:
            built.append((id(self), n_codes))
            alive.append(self)  # an id is unique only while its object lives
        return out

    monkeypatch.setattr(CRF, "inverse", counted_inverse)
    monkeypatch.setattr(CRF, "codes_table", counted_table)
    return calls, built


def _assert_linearised_once(linearisations) -> None:
    """Stored codes reach a response only through its one table per code grid: no other
    evaluation is on more than two values (the half-code limits of a range), and no
    response builds a second table of the same number of codes."""
    calls, built = linearisations
    assert all(table or n <= 2 for _, n, table in calls), sorted({n for _, n, table in calls if not table})
    assert len(built) == len(set(built)), built


def _assert_one_pass(calls: list[str], expected: set[str]) -> None:
    """Each stage called at most once, those ``expected`` exactly once, in :data:`STAGES` order."""
    assert sorted(set(calls), key=STAGES.index) == calls, calls  # once each, in reading order
    assert set(calls) == expected, sorted(set(calls) ^ expected)


def _merge(paths, **options):
    from hdrmerge_cli.api import merge_files

    return merge_files(paths, **options)


#: the stages of a default RAW merge (the noise measured on the bracket; no response, no ghosts)
RAW_STAGES = {"read", "ordered_samples", "estimate_alignment", "choose_alignment", "resolve_exposures", "bracket_noise",
              "choose_models", "reconstruct"}


def test_a_still_raw_bracket_is_decoded_once(dng_bracket, decodes, stage_calls, linearisations, monkeypatch,
                                             tmp_path):
    monkeypatch.setenv("HDRMERGE_CLI_CACHE_DIR", str(tmp_path / "cache"))  # the noise measured, not cached
    folder, meta = dng_bracket
    paths = [str(p) for p in frames_of(folder, meta)]
    _merge(paths)
    assert {p: decodes[p] for p in paths} == {p: 1 for p in paths}
    _assert_one_pass(stage_calls, RAW_STAGES)
    _assert_linearised_once(linearisations)


def test_a_handheld_raw_bracket_is_decoded_once(tmp_path, decodes, stage_calls, linearisations, monkeypatch):
    """Each file decoded once, each stage called once, and each frame's registration image
    made once per resolution (the middle frame's full one serves both of its pairs)."""
    from hdrmerge_cli.pipeline import register

    monkeypatch.setenv("HDRMERGE_CLI_CACHE_DIR", str(tmp_path / "cache"))
    made = []
    for name in ("_linear", "_coarse_linear"):
        def counted(frame, *args, _fn=getattr(register, name), _name=name):
            made.append((_name, frame.path))
            return _fn(frame, *args)

        monkeypatch.setattr(register, name, counted)
    paths = _shifted_dngs(tmp_path, (3.0, -2.0, 0.0, 4.0), times=(0.25, 0.5, 1.0, 2.0))
    merged = _merge(paths, deghost="auto")
    assert merged.bracket.alignment.applied
    assert {p: decodes[p] for p in paths} == {p: 1 for p in paths}
    _assert_one_pass(stage_calls, RAW_STAGES | {"find_ghosts", "choose_deghost"})
    assert len(made) == len(set(made)), sorted(made)  # once per frame and resolution
    assert {p for name, p in made if name == "_linear"} == set(paths)  # every pair registered in full
    _assert_linearised_once(linearisations)


@pytest.mark.parametrize("fixture", ["tiff_bracket", "jpeg_bracket"])
def test_image_brackets_are_decoded_once(request, fixture, decodes, stage_calls, linearisations, monkeypatch, tmp_path):
    """16-bit TIFF (response given by nothing: measured) and JPEG (response measured); the
    JPEG's noise is measured to test its excess variance, which picks its estimator."""
    monkeypatch.setenv("HDRMERGE_CLI_CACHE_DIR", str(tmp_path / "cache"))
    folder, meta = request.getfixturevalue(fixture)
    paths = [str(p) for p in frames_of(folder, meta)]
    _merge(paths)
    assert {p: decodes[p] for p in paths} == {p: 1 for p in paths}
    _assert_one_pass(stage_calls, {"read", "ordered_samples", "measure_response", "estimate_alignment",
                                   "choose_alignment", "resolve_exposures", "bracket_noise", "measure_excess", "choose_models",
                                   "reconstruct"})
    _assert_linearised_once(linearisations)


def test_an_8bit_tiff_bracket_is_decoded_once_with_and_without_a_response(run, tmp_path, decodes):
    run("simulate", "-o", tmp_path, "-q", "--format", "tif", "--size", "192x128", "--frames", "3", "--seed", "2")
    paths = sorted(str(p) for p in tmp_path.glob("frame_*.tif"))
    for crf in (None, "srgb"):
        decodes.clear()
        _merge(paths, crf=crf)
        assert {p: decodes[p] for p in paths} == {p: 1 for p in paths}, crf


def test_times_estimate_resorting_a_handheld_bracket_keeps_each_warp_on_its_frame(tmp_path):
    """The two shortest frames (0.15 EV apart) labelled alike come in the files' order
    longer, shorter: the labels sort them so, the estimates re-sort them after registration
    (the reference, the third, stays); every warp must still move its own frame, so the
    merge matches the one with the true labels."""
    true_times, shifts = (0.45, 0.5, 1.0, 2.0), (4.0, -3.0, 0.0, -6.0)
    paths = _shifted_dngs(tmp_path, shifts, true_times, labels=(0.5, 0.5, 1.0, 2.0))
    given = [paths[1], paths[0], paths[2], paths[3]]  # equal labels keep this order until the estimates
    (tmp_path / "true.txt").write_text("".join(f"{p} {t!r}\n" for p, t in zip(paths, true_times)))
    truth = _merge(given, times_file=str(tmp_path / "true.txt"))
    est = _merge(given, times="estimate")
    assert est.summary()["exposure_check"]["used"] == "estimates"
    assert [f.path for f in est.bracket.frames] == paths  # re-sorted
    for merged in (truth, est):
        assert merged.bracket.alignment.applied and merged.bracket.alignment.reference == paths[2]
        for frame in merged.bracket.frames:  # the scene moved right by dx: the warp's shift is -dx
            dx = shifts[paths.index(frame.path)]
            alignment = merged.bracket.alignment
            assert alignment.warp_of(frame)[0, 2] == pytest.approx(-dx, abs=0.25), alignment.summary()
    a, b = truth.image.astype(np.float64), est.image.astype(np.float64)
    inner = (slice(16, -16), slice(16, -16))
    ok = (a[inner] > 1e-3) & (b[inner] > 1e-3)
    d = np.log(b[inner][ok]) - np.log(a[inner][ok])
    # the same frames moved by the same warps: equal up to the estimated exposures' error
    assert np.sqrt(np.mean((d - np.median(d)) ** 2)) < 0.02


def test_info_decodes_each_frame_once(tiff_bracket, decodes):
    """info's clip classes and its exposure estimates' samples come from one decode."""
    from hdrmerge_cli.pipeline.info import bracket_info

    folder, meta = tiff_bracket
    paths = [str(p) for p in frames_of(folder, meta)]
    out = bracket_info(paths)
    assert len(out["frames"]) == len(paths) and "exposure_estimates" in out
    assert [r["path"] for r in out["frames"]] == sorted(paths, key=lambda p: meta["exposure_times"][paths.index(p)])
    assert {p: decodes[p] for p in paths} == {p: 1 for p in paths}


@pytest.mark.parametrize("shift", [0, 3])
def test_frames_with_alpha_are_decoded_once(run, tmp_path, decodes, shift):
    """RGBA PNGs, transparent over a left stripe (still, and moved ``shift`` px so that the
    registered frames' codes are resampled): the colour and the alpha come from one decode,
    and the output's alpha is the most any frame measured (all of it where another frame
    is opaque)."""
    import OpenImageIO as oiio

    run("simulate", "-o", tmp_path, "-q", "--format", "png", "--size", "160x120", "--frames", "3", "--seed", "3",
        "--times", "0.01,0.04,0.16")
    paths = []
    for k, src in enumerate(sorted(tmp_path.glob("frame_*.png"))):
        px = oiio.ImageBuf(str(src)).get_pixels(oiio.UINT8)
        px = np.roll(px, shift * k, axis=1)
        alpha = np.full(px.shape[:2] + (1,), 255, np.uint8)
        alpha[:, : 10 * (k + 1)] = 0
        spec = oiio.ImageSpec(px.shape[1], px.shape[0], 4, oiio.UINT8)
        spec.alpha_channel = 3
        path = str(tmp_path / f"rgba{k}.png")
        out = oiio.ImageOutput.create(path)
        assert out.open(path, spec) and out.write_image(np.ascontiguousarray(np.concatenate([px, alpha], -1)))
        out.close()
        paths.append(path)
    decodes.clear()
    merged = _merge(paths, times="0.01,0.04,0.16", align="auto" if shift else "off")
    assert {p: decodes[p] for p in paths} == {p: 1 for p in paths}
    assert merged.alpha is not None and merged.alpha[:, :10].max() == 0 and merged.alpha[:, 40:].min() == 1
