"""The input-kind matrix: every kind of frame a camera or scanner writes, through every
command path a user reaches with default options.  Each combination either writes a
finite output or exits 1 or 2 with one error line naming the file or the option, and
leaves nothing behind.  A new default becomes a default only once it passes here."""
from __future__ import annotations

import json
import traceback
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings, strategies as st

from hdrmerge_cli.io.images import read_exr

from benchmarks.input_kinds import linear_dng_bracket
from conftest import _simulate

CHANNELS = (1, 2, 3, 4)  # grey, grey + alpha, RGB, RGBA
BITS = (8, 16)
SIZES = ((1, 1), (1, 7), (7, 1), (48, 64))  # (height, width)


# ---------------------------------------------------------------- making the frames
def _convert(src: Path, dst: Path, channels: int, size: tuple[int, int], alpha_hole: bool = False) -> None:
    """``src`` (an RGB image with EXIF) cropped to ``size`` at its centre and written with
    ``channels`` channels (grey: the green channel; alpha opaque, or 0 over the left third
    with ``alpha_hole``), its EXIF kept."""
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(src))
    spec = buf.spec()
    px = buf.get_pixels(spec.format)
    h, w = size
    y0, x0 = (px.shape[0] - h) // 2, (px.shape[1] - w) // 2
    px = px[y0:y0 + h, x0:x0 + w]
    colour = px[..., 1:2] if channels <= 2 else px[..., :3]
    if channels in (2, 4):
        alpha = np.full(colour.shape[:2] + (1,), np.iinfo(px.dtype).max, px.dtype)
        if alpha_hole:
            alpha[:, : w // 3] = 0
        colour = np.concatenate([colour, alpha], axis=-1)
    out_spec = oiio.ImageSpec(w, h, channels, spec.format)
    for attr in spec.extra_attribs:
        if attr.name.startswith(("Exif:", "ExposureTime", "FNumber", "DateTime", "Make", "Model")):
            out_spec.attribute(attr.name, attr.type, attr.value)
    if channels in (2, 4):
        out_spec.alpha_channel = channels - 1
    out = oiio.ImageOutput.create(str(dst))
    assert out.open(str(dst), out_spec) and out.write_image(np.ascontiguousarray(colour))
    out.close()


@pytest.fixture(scope="module")
def sources(tmp_path_factory, run):
    """Simulated RGB brackets (3 frames 2 EV apart, so neighbours share tones to register
    on; 64 x 48): 8- and 16-bit TIFF, Bayer DNG."""
    root = tmp_path_factory.mktemp("kinds_src")
    out = {}
    times = ("--times", "0.0025,0.01,0.04")
    for bits in BITS:
        meta = _simulate(run, root / f"tif{bits}", "--format", "tif", "--out-bits", str(bits), "--size", "64x48",
                         "--seed", "11", *times)
        out[bits] = [root / f"tif{bits}" / n for n in meta["frames"]]
    meta = _simulate(run, root / "dng", "--size", "64x48", "--seed", "12", *times)
    out["raw"] = [root / "dng" / n for n in meta["frames"]]
    return out


def _image_kind(sources, folder: Path, channels: int, bits: int, size, ext: str | None = None) -> list[Path]:
    """The bracket as ``channels`` x ``bits`` frames cropped to ``size`` (PNG where there is
    an alpha channel, else TIFF, unless ``ext`` says)."""
    folder.mkdir(parents=True, exist_ok=True)
    ext = ext or (".png" if channels in (2, 4) else ".tif")
    paths = []
    for k, src in enumerate(sources[bits]):
        paths.append(folder / f"f{k}{ext}")
        _convert(src, paths[-1], channels, size)
    return paths


# ---------------------------------------------------------------- running and judging
def _invoke(argv) -> tuple[int, str]:
    from hdrmerge_cli.cli import cli

    result = CliRunner().invoke(cli, [str(a) for a in argv], prog_name="hdrmerge-cli")
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        return 99, "Traceback: " + "".join(traceback.format_exception(*result.exc_info))
    return result.exit_code, result.stderr


def _finite_output(path: Path) -> None:
    if path.suffix == ".exr":
        pixels, _ = read_exr(str(path))
        assert pixels.size and np.all(np.isfinite(pixels)), path
    elif path.suffix == ".json":
        json.loads(path.read_text())
    elif path.suffix == ".csv":
        rows = [ln.split(",") for ln in path.read_text().splitlines() if ln and not ln.startswith("#")]
        values = np.array([[float(v) for v in r] for r in rows[1:]])
        assert values.size and np.all(np.isfinite(values)), path
    else:
        assert path.stat().st_size > 0, path


def _paths(kind: str, files: list[Path], out: Path) -> dict[str, tuple[list, list[Path]]]:
    """Each command path a user reaches with default options: argv and the outputs it writes."""
    exr, folder = out / "m.exr", files[0].parent
    paths = {
        "merge": (["merge", *files, "-o", exr], [exr, out / "m.profile.json"]),
        "merge --preview": (["merge", *files, "-o", exr, "--preview", out / "p.jpg"],
                            [exr, out / "m.profile.json", out / "p.jpg"]),
        "merge --batch": (["merge", "--batch", folder, "-o", out / "batch"], []),
        "merge --deghost auto": (["merge", *files, "-o", exr, "--deghost", "auto"], [exr, out / "m.profile.json"]),
        "estimate-crf": (["estimate-crf", *files, "-o", out / "crf.json"], [out / "crf.json"]),
        "calibrate-noise": (["calibrate-noise", *files, "-o", out / "noise.json"], [out / "noise.json"]),
        "info": (["info", *files], []),
        "weights-lut": (["weights-lut", *files, "-o", out / "lut.csv"], [out / "lut.csv"]),
    }
    if kind == "image":  # the noise of images is measured through a response
        paths["calibrate-noise --crf srgb"] = (["calibrate-noise", *files, "--crf", "srgb", "-o", out / "noise.json"],
                                               [out / "noise.json"])
    if kind == "raw":
        paths["merge -o x.dng"] = (["merge", *files, "-o", out / "m.dng"], [out / "m.dng", out / "m.profile.json"])
        paths["merge --cfa"] = (["merge", *files, "-o", exr, "--cfa"], [exr, out / "m.profile.json"])
    return paths


def _check(argv, outputs: list[Path], out: Path, names: list[str]) -> None:
    code, stderr = _invoke(argv)
    assert "Traceback" not in stderr and "internal error" not in stderr, stderr
    if code == 0:
        for path in outputs:
            _finite_output(path)
        for path in (out / "batch").glob("*.exr"):
            _finite_output(path)
        return
    assert code in (1, 2), stderr
    errors = [ln for ln in stderr.splitlines() if ln.startswith(("Error:", "hdrmerge-cli: error:"))]
    if argv[1] == "--batch":  # one line per bracket that failed, then the count
        assert len(errors) >= 2 and "failed" in errors[-1], stderr
        assert all(any(n in e for n in names) for e in errors[:-1]), stderr
    else:
        assert len(errors) == 1, stderr
        assert any(n in errors[0] for n in names) or "--" in errors[0], stderr
    assert not any(p.exists() for p in outputs), stderr


def _every_command(files: list[Path], kind: str, tmp_path: Path) -> None:
    for name in _paths(kind, files, tmp_path):
        out = tmp_path / "".join(c for c in name if c.isalnum())
        out.mkdir()
        argv, outputs = _paths(kind, files, out)[name]
        _check(argv, outputs, out, [f.name for f in files])


IMAGE_KINDS = [(c, b, s) for c in CHANNELS for b in BITS for s in SIZES]


@pytest.mark.parametrize("channels, bits, size", IMAGE_KINDS,
                         ids=[f"{c}ch-{b}bit-{s[0]}x{s[1]}" for c, b, s in IMAGE_KINDS])
def test_image_kinds_through_every_command(sources, tmp_path, channels, bits, size):
    _every_command(_image_kind(sources, tmp_path / "in", channels, bits, size), "image", tmp_path)


@pytest.mark.parametrize("kind", ["raw", "linear-rgb", "linear-mono"])
def test_raw_kinds_through_every_command(sources, tmp_path, kind):
    if kind == "raw":  # the frames alone in a folder (the simulator's holds its truth EXR too)
        (tmp_path / "in").mkdir()
        files = [tmp_path / "in" / f.name for f in sources["raw"]]
        for src, dst in zip(sources["raw"], files):
            dst.symlink_to(src)
    else:
        files = linear_dng_bracket(tmp_path / "in", kind == "linear-mono", (48, 64))
    _every_command(files, "raw" if kind == "raw" else "linear", tmp_path)


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(channels=st.sampled_from(CHANNELS), bits=st.sampled_from(BITS), h=st.integers(1, 48), w=st.integers(1, 64))
def test_merge_any_size_and_layout(sources, tmp_path_factory, channels, bits, h, w):
    """Default merge of any crop of a bracket, any channel layout: a finite EXR, or one line."""
    folder = tmp_path_factory.mktemp("any")
    files = _image_kind(sources, folder / "in", channels, bits, (h, w))
    _check(["merge", *files, "-o", folder / "m.exr"], [folder / "m.exr"], folder, [f.name for f in files])


@pytest.mark.parametrize("bits", BITS)
def test_monochrome_default_merge_equals_unaligned_merge(sources, tmp_path, bits):
    """Nothing moved: a grey bracket merged with default options (alignment on) is the same
    merge as with ``--align off``, to float rounding."""
    files = _image_kind(sources, tmp_path / "in", 1, bits, (48, 64))
    results = []
    for align in ("auto", "off"):
        exr = tmp_path / f"{align}.exr"
        code, stderr = _invoke(["merge", *files, "-o", exr, "--align", align, "--crf", "srgb"])
        assert code == 0, stderr
        results.append(read_exr(str(exr))[0])
    assert results[0].shape == (48, 64, 1)
    np.testing.assert_allclose(results[0], results[1], rtol=1e-6)


def test_a_moved_grey_frame_is_registered(tmp_path, run):
    """Alignment on monochrome frames: a grey frame moved by (-5, +3) px is found."""
    import OpenImageIO as oiio

    meta = _simulate(run, tmp_path / "rgb", "--format", "tif", "--size", "320x240", "--times", "0.0025,0.01,0.04",
                     "--seed", "13")
    files = []
    for k, name in enumerate(meta["frames"]):
        buf = oiio.ImageBuf(str(tmp_path / "rgb" / name))
        grey = buf.get_pixels(oiio.UINT8)[..., 1:2]
        if k == 2:
            grey = np.roll(grey, (3, -5), axis=(0, 1))
        spec = oiio.ImageSpec(320, 240, 1, oiio.UINT8)
        spec.attribute("ExposureTime", buf.spec().getattribute("ExposureTime"))
        files.append(tmp_path / f"g{k}.tif")
        out = oiio.ImageOutput.create(str(files[-1]))
        assert out.open(str(files[-1]), spec) and out.write_image(np.ascontiguousarray(grey))
        out.close()
    proc = run("merge", *files, "-o", tmp_path / "m.exr", "--crf", "srgb", "--json", "--deghost", "auto")
    alignment = json.loads(proc.stdout)["alignment"]
    assert alignment["applied"]
    np.testing.assert_allclose(alignment["shift_px"][2], [-5, 3], atol=0.1)
    np.testing.assert_allclose(alignment["shift_px"][0], [0, 0], atol=0.1)


def test_alpha_zero_pixels_carry_no_weight(sources, tmp_path):
    """RGBA: where a frame's alpha is 0 the merge is that of the other frames alone, whatever
    colour the transparent pixels store."""
    import OpenImageIO as oiio

    rgba = _image_kind(sources, tmp_path / "rgba", 4, 8, (48, 64), ".tif")  # PNG rounds the EXIF times
    middle = rgba[1]
    buf = oiio.ImageBuf(str(middle))
    px = buf.get_pixels(oiio.UINT8).copy()
    px[:, :20, 3] = 0
    px[:, :20, :3] = 200  # junk under the transparency
    spec = buf.spec()
    out = oiio.ImageOutput.create(str(middle))
    assert out.open(str(middle), spec) and out.write_image(px)
    out.close()
    rgb = _image_kind(sources, tmp_path / "rgb", 3, 8, (48, 64))
    common = ["--crf", "srgb", "--noise", "sigma_o2=4,alpha=1,beta=0", "--reference", "shortest", "--estimator", "log"]
    merged = {}
    for name, files in (("rgba", rgba), ("pair", [rgb[0], rgb[2]]), ("all", rgb)):
        code, stderr = _invoke(["merge", *files, "-o", tmp_path / f"{name}.exr", *common])
        assert code == 0, stderr
        merged[name] = read_exr(str(tmp_path / f"{name}.exr"))[0]
    # the output's alpha: the most any frame measured of each pixel (all of it: two frames are opaque)
    assert merged["rgba"].shape[-1] == 4 and np.all(merged["rgba"][..., 3] == 1)
    np.testing.assert_allclose(merged["rgba"][:, :20, :3], merged["pair"][:, :20], rtol=1e-6)
    np.testing.assert_allclose(merged["rgba"][:, 20:, :3], merged["all"][:, 20:], rtol=1e-6)


@pytest.mark.parametrize("left, right, words", [
    (0, 0, "every pixel reads black in every frame; the output holds only an upper bound"),
    (255, 255, "every pixel is clipped in every frame; the output holds only a lower bound"),
    (0, 255, "no pixel is measured in any frame (50.0 % read black in every frame, 50.0 % are clipped"),
])
def test_degenerate_brackets_say_what_the_output_holds(tmp_path, left, right, words):
    """All black, all clipped, or nothing measured anywhere: a finite EXR and one warning."""
    import OpenImageIO as oiio

    files = []
    for k, t in enumerate((0.01, 0.04, 0.16)):
        spec = oiio.ImageSpec(16, 8, 3, oiio.UINT8)
        spec.attribute("ExposureTime", t)
        codes = np.full((8, 16, 3), left, np.uint8)
        codes[:, 8:] = right
        files.append(tmp_path / f"f{k}.tif")
        out = oiio.ImageOutput.create(str(files[-1]))
        assert out.open(str(files[-1]), spec) and out.write_image(codes)
        out.close()
    code, stderr = _invoke(["merge", *files, "-o", tmp_path / "m.exr", "--crf", "srgb"])
    assert code == 0, stderr
    warnings = [ln for ln in stderr.splitlines() if "warning" in ln]
    assert len(warnings) == 1 and words in warnings[0], stderr
    _finite_output(tmp_path / "m.exr")


def test_float_tiff_kinds_are_refused_in_one_line(sources, tmp_path):
    """Float TIFFs (half and float, as OpenImageIO reads them) are not code values: every
    command refuses them in one line naming the file."""
    import OpenImageIO as oiio

    for fmt in ("half", "float"):
        folder = tmp_path / fmt / "in"
        folder.mkdir(parents=True)
        files = []
        for k, src in enumerate(sources[16]):
            buf = oiio.ImageBuf(str(src))
            files.append(folder / f"f{k}.tif")
            assert buf.write(str(files[-1]), fmt)
        for name in _paths("image", files, tmp_path / fmt):
            out = tmp_path / fmt / "".join(c for c in name if c.isalnum())
            out.mkdir()
            argv, outputs = _paths("image", files, out)[name]
            _check(argv, outputs, out, [f.name for f in files])
