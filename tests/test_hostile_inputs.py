"""Hostile values and files given to the six commands: extreme numbers, frames that are
not what their option says, unwritable or full outputs, config files.  Each is refused in
one line that names the user's file or option and the true reason (exit 1 for data, 2 for
usage), with no traceback and nothing written."""
import errno
import json
import os
import pathlib
import traceback

import numpy as np
import pytest
from click.testing import CliRunner

from conftest import SHARED, frames_of, needs_shared, save_profile
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.io.atomic import atomic_paths
from hdrmerge_cli.io.profile import KIND
from hdrmerge_cli.pipeline.lut import check_luts


def _cli(*argv):
    """(exit code, stderr) of ``hdrmerge-cli argv`` run in this process; an uncaught
    exception is exit 99 with its traceback."""
    from hdrmerge_cli.cli import cli

    result = CliRunner().invoke(cli, [str(a) for a in argv], prog_name="hdrmerge-cli")
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        return 99, "Traceback: " + "".join(traceback.format_exception(*result.exc_info))
    return result.exit_code, result.stderr


def _refused(code, stderr, expected_code, words=(), absent=()):
    """One error line (warnings aside) holding ``words`` and none of ``absent``."""
    assert code == expected_code, stderr
    assert "Traceback" not in stderr
    errors = [ln for ln in stderr.splitlines() if ln.startswith(("Error:", "hdrmerge-cli: error:"))]
    assert len(errors) == 1, stderr
    if expected_code == 1:
        assert [ln for ln in stderr.strip().splitlines() if "warning" not in ln] == errors, stderr
    for word in words:
        assert word in errors[0], stderr
    for word in absent:
        assert word not in stderr, stderr
    return errors[0]


def _nothing_written(folder):
    assert not [p for p in pathlib.Path(folder).iterdir() if p.name.startswith(("out", ".out")) or ".part" in p.name]


# ---------------------------------------------------------------- extreme numeric options
EDGE_CASES = {
    "lambda overflow": (["estimate-crf", "{IMG}", "--lambda", "1e300"], ["--lambda"]),
    "coupling overflow": (["estimate-crf", "{IMG}", "--coupling", "1e300"], ["--coupling"]),
    "negative seed": (["estimate-crf", "{IMG}", "--seed", "-1"], ["--seed"]),
    "prior rate underflow": (["weights-lut", "--times", "0.01,0.1,1", "--weights", "probabilistic", "--noise",
                              "sigma_o2=4,alpha=1", "--prior-rate", "1e-308"], ["--prior-rate"]),
    "prior rate overflow": (["weights-lut", "--times", "0.01,0.1,1", "--weights", "probabilistic", "--noise",
                             "sigma_o2=4,alpha=1", "--prior-rate", "1e308"], ["--prior-rate"]),
    "scale overflow": (["simulate", "--size", "64x64", "--scale", "1e300"], ["--scale"]),
    "alpha overflow": (["simulate", "--size", "64x64", "--alpha", "1e300"], ["--alpha"]),
    "sigma_o2 overflow": (["simulate", "--size", "64x64", "--sigma-o2", "1e300"], ["--sigma-o2"]),
    "iso overflow": (["simulate", "--size", "64x64", "--iso", str(10**20)], ["--iso"]),
    "simulate negative seed": (["simulate", "--size", "64x64", "--seed", "-1"], ["--seed"]),
    "size overflow": (["simulate", "--size", "10000000000x10000000000"], ["--size"]),
}


@pytest.mark.parametrize("name", list(EDGE_CASES))
def test_extreme_numbers_are_refused_where_they_are_read(tmp_path, jpeg_bracket, name):
    args, words = EDGE_CASES[name]
    frames = [str(p) for p in frames_of(*jpeg_bracket)]
    argv = [a for arg in args for a in (frames if arg == "{IMG}" else [arg])]
    out = tmp_path / {"estimate-crf": "out.json", "weights-lut": "out.csv"}.get(args[0], "out")
    _refused(*_cli(*argv, "-o", out), 2, words)
    _nothing_written(tmp_path)


# ---------------------------------------------------------------- calibrate-noise: darks that are not dark
@pytest.fixture(scope="module")
def flats_and_darks(tmp_path_factory, run):
    root = tmp_path_factory.mktemp("ptc")
    run("simulate", "-q", "-o", root / "flats", "--scene", "flat", "--scale", "1000", "--size", "96x96", "--frames",
        "3", "--repeat", "2")
    run("simulate", "-q", "-o", root / "darks", "--scene", "dark", "--size", "96x96", "--frames", "2")
    return root


def test_flats_given_as_darks_are_refused(run, tmp_path, flats_and_darks):
    """Flat fields as --darks made their photon noise the read noise (sigma_o2 ~ 2170 for
    a sensor of 9, exit 0); real darks still give the sensor's."""
    root = flats_and_darks
    out = tmp_path / "out.json"
    proc = run("calibrate-noise", "--darks", root / "flats", "--flats", root / "flats", "-o", out, check=False)
    line = _refused(proc.returncode, proc.stderr, 1, ["not a dark frame", "above the black level", "--darks"])
    assert str(root / "flats" / "frame_00.dng") in line
    _nothing_written(tmp_path)
    summary = json.loads(run("calibrate-noise", "--darks", root / "darks", "--flats", root / "flats", "-o", out,
                             "--json").stdout)
    for fit in summary["noise"]["ISO100"].values():
        assert fit["sigma_o2"] == pytest.approx(9.0, rel=0.3)


# ---------------------------------------------------------------- weights-lut: tables with no weight
def test_weights_lut_refuses_a_column_of_zero_weights(tmp_path):
    out = tmp_path / "out.csv"
    _refused(*_cli("weights-lut", "--times", "0.01,0.1,1", "--weights", "probabilistic", "--noise",
                   "sigma_o2=4,alpha=1", "--prior-rate", "1e-3", "-o", out), 1,
             ["--prior-rate 0.001", "zero at every code", "t=0.01"])
    _nothing_written(tmp_path)
    code, _ = _cli("weights-lut", "--times", "0.01,0.1,1", "--weights", "probabilistic", "--noise",
                   "sigma_o2=4,alpha=1", "--prior-rate", "1e4", "-o", out)
    assert code == 0 and np.loadtxt(out, delimiter=",", skiprows=1)[:, 1:].max(axis=0).min() > 0


def test_a_table_without_weight_is_refused_without_a_prior_too():
    table = np.zeros((4, 2))
    table[1:3, 0] = 0.5
    with pytest.raises(HdrMergeError, match="t=2 are zero at every code"):
        check_luts(table, ["t=1", "t=2"], "bounded")
    check_luts(np.full((4, 2), 0.5), ["t=1", "t=2"], "bounded")


# ---------------------------------------------------------------- outputs that cannot be written
def test_a_read_only_folder_names_the_users_path(tmp_path, monkeypatch):
    real_open = os.open

    def refuse(path, *args, **kwargs):
        if ".part" in str(path):
            raise PermissionError(errno.EACCES, "Permission denied", path)
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(os, "open", refuse)
    out = tmp_path / "out.exr"
    with pytest.raises(HdrMergeError) as info:
        with atomic_paths([out, tmp_path / "out.profile.json"], False):
            pass
    assert str(info.value) == f"{out}: cannot write (Permission denied)"
    assert not list(tmp_path.iterdir())


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_folder_through_the_command(tmp_path, jpeg_bracket):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        line = _refused(*_cli("merge", *frames_of(*jpeg_bracket), "--crf", "srgb", "-o", folder / "out.exr"), 1,
                        [str(folder / "out.exr"), "cannot write"], absent=[".part"])
        assert "Permission denied" in line
    finally:
        folder.chmod(0o755)


def _disk_full(monkeypatch):
    """Path.write_text fails as a full disk does: an OSError naming no file."""
    real = pathlib.Path.write_text

    def write_text(self, *args, **kwargs):
        if ".part" in self.name:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(pathlib.Path, "write_text", write_text)


def test_a_full_disk_names_the_profile(tmp_path, monkeypatch):
    _disk_full(monkeypatch)
    out = tmp_path / "out.json"
    with pytest.raises(HdrMergeError) as info:
        save_profile(out, {"schema": 1, "kind": KIND, "crf": {"model": "srgb"}}, False)
    assert str(info.value) == f"{out}: cannot write (No space left on device)"
    assert not list(tmp_path.iterdir())


def test_a_full_disk_while_merging_names_the_profile(tmp_path, monkeypatch, jpeg_bracket):
    _disk_full(monkeypatch)
    _refused(*_cli("merge", *frames_of(*jpeg_bracket), "--crf", "srgb", "-o", tmp_path / "out.exr"), 1,
             [f"{tmp_path / 'out.profile.json'}: cannot write (No space left on device)"], absent=["None", ".part"])
    assert not list(tmp_path.iterdir())


# ---------------------------------------------------------------- invalid camera responses
def _table_profile(path, values):
    path.write_text(json.dumps({"schema": 1, "kind": KIND, "crf": {"model": "table", "inverse": [values]}}))
    return path


@pytest.mark.parametrize("how", ["csv", "profile", "crf profile", "gamma", "profile gamma"])
def test_an_invalid_response_is_named_not_blamed_on_the_reference(tmp_path, jpeg_bracket, how):
    neg = list(np.linspace(-0.2, 1.0, 256))
    if how == "csv":
        (tmp_path / "neg.csv").write_text("z,linear\n0,-1\n128,-0.5\n255,1\n")
        args, words = ["--crf", tmp_path / "neg.csv"], ["neg.csv", "negative"]
    elif how in ("profile", "crf profile"):
        prof = _table_profile(tmp_path / "neg.json", neg)
        args, words = ["--profile" if how == "profile" else "--crf", prof], ["neg.json", "negative"]
    elif how == "gamma":
        args, words = ["--crf", "gamma:1e300"], ["--crf gamma:1e300", "stops"]
    else:
        (tmp_path / "g.json").write_text(json.dumps({"schema": 1, "kind": KIND,
                                                     "crf": {"model": "gamma", "gamma": 1e300}}))
        args, words = ["--profile", tmp_path / "g.json"], ["g.json", "crf/gamma"]
    _refused(*_cli("merge", *frames_of(*jpeg_bracket), *args, "-o", tmp_path / "out.exr"), 1,
             ["not a valid response", *words], absent=["--reference"])
    _nothing_written(tmp_path)


# ---------------------------------------------------------------- simulate
def test_a_size_too_large_for_memory_says_so_up_front(tmp_path, monkeypatch):
    import hdrmerge_cli.pipeline.simulate as sim

    monkeypatch.setattr(sim, "available_memory", lambda: 10**8)
    line = _refused(*_cli("simulate", "--size", "1000x1000", "-o", tmp_path / "out"), 1,
                    ["--size 1000x1000", "GB of memory", "0.1 GB available"], absent=["merge fewer"])
    assert "0.17 GB" in line
    assert not (tmp_path / "out").exists()


def test_the_size_has_an_upper_bound(tmp_path):
    _refused(*_cli("simulate", "--size", "100000x100000", "-o", tmp_path / "out"), 2, ["--size", "65500"])


@pytest.mark.parametrize("extra", [[], ["--scale", "1e9", "--format", "jpg"]])
def test_too_many_frames_are_blamed_on_the_frames(tmp_path, extra):
    """--frames 64 one stop apart span 63 stops: refused as too many frames (naming the
    limit), not as 'too dark, raise --scale' nor as an internal error at --scale 1e9."""
    line = _refused(*_cli("simulate", "--size", "64x64", "--frames", "64", *extra, "-o", tmp_path / "out"), 1,
                    ["--frames 64", "63 stops", "all clipped", "--frames 17 or fewer"],
                    absent=["raise --scale", "internal error"])
    assert "builtin covers" in line
    assert not (tmp_path / "out").exists()


def test_scenes_too_bright_or_dark_say_which(tmp_path):
    _refused(*_cli("simulate", "--size", "64x64", "--scale", "1e9", "-o", tmp_path / "out"), 1,
             ["too bright", "lower --scale"])
    _refused(*_cli("simulate", "--size", "64x64", "--scale", "1e-9", "-o", tmp_path / "out"), 1,
             ["too dark", "raise --scale"])
    _refused(*_cli("simulate", "--size", "64x64", "--times", "1e-9", "-o", tmp_path / "out"), 1,
             ["--times", "DNG"], absent=["--scale"])
    _refused(*_cli("simulate", "--size", "64x64", "--times", "1e-9", "--format", "jpg", "-o", tmp_path / "out"), 1,
             ["1e-09 s", "JPG", "longer --times"], absent=["internal error"])
    assert not (tmp_path / "out").exists()


def test_an_ldr_image_is_not_a_scene(tmp_path, jpeg_bracket):
    """A JPEG as --scene: refused as display-referred (tone-curved, clipped: its highlights
    are lost), not reported as 'too dark' after the fact; a float EXR is a scene."""
    folder, meta = jpeg_bracket
    line = _refused(*_cli("simulate", "--scene", frames_of(folder, meta)[0], "-o", tmp_path / "out"), 1,
                    ["frame_00.jpg", "display-referred", "scene-linear"], absent=["too dark"])
    assert "uint8" in line
    assert not (tmp_path / "out").exists()
    code, stderr = _cli("simulate", "--scene", folder / "truth.exr", "--scale", "1e5", "--frames", "3", "-q",
                        "-o", tmp_path / "exr")
    assert code == 0 and (tmp_path / "exr" / "frame_02.dng").exists(), stderr


def test_huge_photon_counts_are_clipped_not_a_traceback(tmp_path):
    code, stderr = _cli("simulate", "--size", "64x64", "--times", "1,2", "--scale", "1e12", "-q",
                        "-o", tmp_path / "out")
    assert code == 0, stderr
    assert json.loads((tmp_path / "out" / "simulation.json").read_text())["saturated_fraction"] == [1.0, 1.0]


def test_downscale_beyond_the_scene_names_downscale(tmp_path):
    _refused(*_cli("simulate", "--size", "64x64", "--downscale", "64", "-o", tmp_path / "out"), 1,
             ["--downscale 64", "1 x 1"], absent=["black"])


def test_an_output_folder_that_cannot_be_made(tmp_path):
    (tmp_path / "file").write_text("")
    _refused(*_cli("simulate", "--size", "64x64", "-o", tmp_path / "file" / "sub"), 1,
             [str(tmp_path / "file" / "sub"), "cannot create the folder"])


# ---------------------------------------------------------------- estimate-crf
def test_too_few_samples_are_refused_not_judged(tmp_path, jpeg_bracket):
    """--samples 1 is refused: a response cannot be fitted from one pixel (nor are the
    labels then judged through such a fit)."""
    for method in ("debevec", "goossens"):
        _refused(*_cli("estimate-crf", *frames_of(*jpeg_bracket), "--method", method, "--samples", "1",
                       "-o", tmp_path / "out.json"), 1, ["--samples 1", "at least 128"], absent=["labelled"])
    _nothing_written(tmp_path)


def test_a_flat_fit_is_refused(tmp_path, jpeg_bracket):
    """debevec with --lambda 1e6 on 128 samples fits a response flat within a stop: every
    code would merge to about white."""
    _refused(*_cli("estimate-crf", *frames_of(*jpeg_bracket), "--method", "debevec", "--samples", "128",
                   "--lambda", "1e6", "-o", tmp_path / "out.json"), 1, ["flat", "--lambda"])
    _nothing_written(tmp_path)


# ---------------------------------------------------------------- --config
@pytest.mark.parametrize("command, toml, code, words", [
    ("estimate-crf", "lambda = -1\n", 2, ["--lambda", "c.toml"]),
    ("estimate-crf", "lambda = 1e300\n", 2, ["--lambda", "c.toml"]),
    ("merge", "[merge]\nnoise = \"sigma_o2=nan,alpha=1\"\n", 1, ["--noise", "c.toml"]),
    ("merge", "crf = \"gamma:1e300\"\n", 1, ["gamma:1e300", "c.toml"]),
    ("merge", "weights = \"best\"\n", 2, ["--weights", "c.toml"]),
])
def test_config_values_name_the_config_file(tmp_path, jpeg_bracket, command, toml, code, words):
    (tmp_path / "c.toml").write_text(toml)
    out = tmp_path / ("out.json" if command == "estimate-crf" else "out.exr")
    _refused(*_cli(command, *frames_of(*jpeg_bracket), "--config", tmp_path / "c.toml", "-o", out), code, words)
    _nothing_written(tmp_path)


def test_a_value_on_the_command_line_does_not_blame_the_config(tmp_path, jpeg_bracket):
    (tmp_path / "c.toml").write_text("crf = \"srgb\"\n")
    line = _refused(*_cli("merge", *frames_of(*jpeg_bracket), "--config", tmp_path / "c.toml", "--noise",
                          "sigma_o2=nan,alpha=1", "-o", tmp_path / "out.exr"), 1, ["--noise"])
    assert "c.toml" not in line


# ---------------------------------------------------------------- other hostile files
@pytest.mark.parametrize("name, content", [
    ("empty.csv", ""), ("list.json", "[1]"), ("nulls.json", '{"weights": [[null, 1]]}'),
    ("deep.json", '{"weights": ' + "[" * 100000 + "]" * 100000 + "}"),
])
def test_bad_weight_tables(tmp_path, jpeg_bracket, name, content):
    (tmp_path / name).write_text(content)
    _refused(*_cli("merge", *frames_of(*jpeg_bracket), "--crf", "srgb", "--lut", tmp_path / name,
                   "-o", tmp_path / "out.exr"), 1, [name], absent=["UserWarning"])
    _nothing_written(tmp_path)


@pytest.mark.parametrize("what", ["folder", "image"])
def test_a_crf_that_is_a_folder_or_an_image(tmp_path, jpeg_bracket, what):
    folder, meta = jpeg_bracket
    spec = tmp_path if what == "folder" else folder / "truth.exr"
    _refused(*_cli("weights-lut", "--times", "1,2", "--crf", spec, "-o", tmp_path / "out.csv"), 1,
             [str(spec), "not a camera response" if what == "image" else "is a folder"], absent=["unknown CRF"])
    _nothing_written(tmp_path)



@pytest.mark.parametrize("fmt", ["jpg", "dng"])
def test_a_read_only_simulate_folder_names_it(tmp_path, monkeypatch, fmt):
    """The JPEG exposure-time probe and the outputs' temporaries are hidden names in the
    folder: the error names the folder or the user's file, never them."""
    out = tmp_path / "out"
    out.mkdir()
    real_open = os.open

    def refuse(path, *args, **kwargs):
        if os.path.dirname(os.fspath(path)) == str(out):
            raise PermissionError(errno.EACCES, "Permission denied", path)
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(os, "open", refuse)
    _refused(*_cli("simulate", "--size", "64x64", "--format", fmt, "-o", out), 1,
             [str(out), "cannot write (Permission denied)"], absent=[".probe", ".part"])
    assert not list(out.iterdir())


@pytest.mark.parametrize("value, words, absent", [(0, "100.0 % of its pixels read black", "clipped at"),
                                                  (255, "100.0 % of its pixels are clipped at white", "read black")])
def test_black_frames_are_not_called_clipped(tmp_path, value, words, absent):
    """calibrate-noise on frames with nothing to measure says whether they are black or white."""
    import OpenImageIO as oiio

    files = []
    for k, t in enumerate((0.01, 0.04)):
        spec = oiio.ImageSpec(16, 8, 3, oiio.UINT8)
        spec.attribute("ExposureTime", t)
        files.append(tmp_path / f"f{k}.tif")
        out = oiio.ImageOutput.create(str(files[-1]))
        assert out.open(str(files[-1]), spec) and out.write_image(np.full((8, 16, 3), value, np.uint8))
        out.close()
    code, stderr = _cli("calibrate-noise", *files, "--crf", "srgb", "-o", tmp_path / "n.json")
    assert code == 1 and "Traceback" not in stderr
    skipped = [ln for ln in stderr.splitlines() if "skipped" in ln]
    assert len(skipped) == 2 and all(words in ln and absent not in ln for ln in skipped), stderr
    assert not (tmp_path / "n.json").exists()


# ---------------------------------------------------------------- the hostile run's leftovers (issue 49)
def test_calibrate_noise_refuses_frames_of_two_sizes_before_any_array(tmp_path, flats_and_darks):
    """A bracket of two sizes, and flats of two sizes: one line naming the frame, nothing
    compared pixel by pixel."""
    small, large = tmp_path / "s", tmp_path / "l"
    _cli("simulate", "-q", "-o", small, "--size", "64x64", "--frames", "2", "--seed", "1")
    _cli("simulate", "-q", "-o", large, "--size", "96x64", "--frames", "2", "--seed", "1", "--times", "0.5,0.9")
    line = _refused(*_cli("calibrate-noise", small / "frame_00.dng", large / "frame_01.dng", "-o", tmp_path / "out.json"),
                    1, ["size 96x64 differs from 64x64", "pixel by pixel"])
    assert str(large / "frame_01.dng") in line
    flats = tmp_path / "flats"
    flats.mkdir()
    for k, f in enumerate(sorted((flats_and_darks / "flats").glob("*.dng"))[:2]):
        (flats / f"a{k}.dng").write_bytes(f.read_bytes())
    _cli("simulate", "-q", "-o", tmp_path / "f2", "--scene", "flat", "--scale", "1000", "--size", "64x96",
         "--frames", "2")
    for f in sorted((tmp_path / "f2").glob("*.dng")):
        (flats / f"b{f.name}").write_bytes(f.read_bytes())
    _refused(*_cli("calibrate-noise", "--flats", flats, "--darks", flats_and_darks / "darks", "-o",
                   tmp_path / "out.json"), 1, ["size", "differs from", "pixel by pixel"])
    _nothing_written(tmp_path)


def test_cfa_on_an_image_bracket_says_it_writes_rgb(tmp_path, jpeg_bracket):
    folder, meta = jpeg_bracket
    code, stderr = _cli("merge", *frames_of(folder, meta), "--cfa", "-o", tmp_path / "m.exr")
    assert code == 0 and "--cfa" in stderr and "camera-processed image" in stderr and "writing RGB" in stderr


def test_lut_names_itself_in_the_header_and_profile_not_the_unused_weights(tmp_path, jpeg_bracket):
    import OpenImageIO as oiio

    folder, meta = jpeg_bracket
    frames = frames_of(folder, meta)
    lut = tmp_path / "w.csv"
    code, stderr = _cli("weights-lut", *frames, "-o", lut)
    assert code == 0, stderr
    code, stderr = _cli("merge", *frames, "--lut", lut, "--weights", "triangle", "-o", tmp_path / "m.exr")
    assert code == 0 and "--weights triangle is not used" in stderr, stderr
    header = oiio.ImageInput.open(str(tmp_path / "m.exr")).spec().getattribute("hdrmerge:weights")
    assert header == "lut:w.csv"
    assert json.loads((tmp_path / "m.profile.json").read_text())["weights"] == "lut:w.csv"


@pytest.mark.parametrize("fmt", ["jpg", "dng"])
def test_simulate_refuses_16_bit_output_its_format_cannot_hold(tmp_path, fmt):
    _refused(*_cli("simulate", "--format", fmt, "--out-bits", "16", "--size", "64x64", "-o", tmp_path / "out"), 2,
             ["--out-bits"])
    assert not (tmp_path / "out").exists()


def test_plan_refuses_metering_frames_at_an_iso_the_profile_lacks(tmp_path):
    from hdrmerge_cli.core.crf import CRF
    from hdrmerge_cli.io.profile import new_profile

    _cli("simulate", "-q", "-o", tmp_path / "m", "--size", "128x96", "--frames", "3", "--iso", "400", "--seed", "2")
    profile = tmp_path / "cam.json"
    prof = new_profile({"make": "hdrmerge-cli", "model": "simulated sensor"}, 14, CRF("linear"), [], "test")
    profile.write_text(json.dumps(prof | {"noise": {"ISO100": {c: {"sigma_o2": 9.0, "alpha": 0.25, "beta": 0.0}
                                                               for c in "RGB"}}}))
    _refused(*_cli("plan", *sorted((tmp_path / "m").glob("*.dng")), "--profile", profile, "--time", "0.5"), 1,
             [str(profile), "ISO400", "ISO100"])


@needs_shared
def test_calibrate_noise_refuses_one_textured_photograph(tmp_path):
    """One DNG of a textured scene: its local statistics read texture as noise (sigma_o2 of
    0 or 2e5 against 9); refused, naming the frame and what would measure the noise."""
    folder = tmp_path / "one"
    _cli("simulate", "-q", "-o", folder, "--frames", "1", "--seed", "4", "--scene",
         SHARED / "hdr" / "ScanLines_StillLife.exr", "--downscale", "4", "--scale", "20000")
    line = _refused(*_cli("calibrate-noise", folder / "frame_00.dng", "-o", tmp_path / "out.json"), 1,
                    ["do not pin the noise", "+/-", "two or more exposures", "--flats"])
    assert str(folder / "frame_00.dng") in line
    _nothing_written(tmp_path)


def test_calibrate_noise_on_flats_without_darks_states_the_read_noise_uncertainty(tmp_path):
    flats = tmp_path / "flats"
    _cli("simulate", "-q", "-o", flats, "--scene", "flat", "--scale", "300", "--size", "96x96", "--frames", "5",
         "--repeat", "2")
    code, stderr = _cli("calibrate-noise", "--flats", flats, "-o", tmp_path / "n.json")
    assert code == 0 and "without --darks" in stderr and "+/-" in stderr, stderr
    noise = json.loads((tmp_path / "n.json").read_text())["noise"]["ISO100"]
    for entry in noise.values():
        se = entry["stderr"]["sigma_o2"]
        assert se > 0 and abs(entry["sigma_o2"] - 9.08) < 4 * se


def test_a_dng_smaller_than_libraw_reads_says_so(tmp_path):
    from hdrmerge_cli.io.dng_integer import write_dng

    path = tmp_path / "tiny.dng"
    write_dng(str(path), np.full((3, 3), 1000, np.uint16), pattern="RGGB", black=512, white=16383,
              exposure_time=0.01, iso=100, aperture=8.0)
    _refused(*_cli("info", path), 1, [str(path), "3 x 3 pixels", "at least 32 x 32"])


@pytest.mark.parametrize("name", ["dir.csv", "dir.json"])
def test_a_crf_folder_named_like_a_table_is_a_folder(tmp_path, jpeg_bracket, name):
    folder, meta = jpeg_bracket
    (tmp_path / name).mkdir()
    _refused(*_cli("merge", *frames_of(folder, meta), "--crf", tmp_path / name, "-o", tmp_path / "out.exr"), 1,
             ["is a folder"], absent=["no such file"])


def _flat_tiffs(tmp_path, value, times=(0.01, 0.04, 0.16), size=(64, 48)):
    import OpenImageIO as oiio

    files = []
    for k, t in enumerate(times):
        spec = oiio.ImageSpec(size[0], size[1], 3, oiio.UINT8)
        spec.attribute("ExposureTime", t)
        files.append(tmp_path / f"v{value}_{k}.tif")
        out = oiio.ImageOutput.create(str(files[-1]))
        assert out.open(str(files[-1]), spec) and out.write_image(np.full((size[1], size[0], 3), value, np.uint8))
        out.close()
    return files


@pytest.mark.parametrize("value, words", [(0, "read black"), (255, "clipped at white")])
def test_estimate_crf_on_black_or_white_frames_names_the_frame_not_the_spacing(tmp_path, value, words):
    files = _flat_tiffs(tmp_path, value)
    _refused(*_cli("estimate-crf", *files, "-o", tmp_path / "out.csv"), 1, [words, "too few unclipped"],
             absent=["too far apart"])


def test_calibrate_noise_on_a_one_pixel_frame_says_it_is_too_small_not_black(tmp_path):
    files = _flat_tiffs(tmp_path, 100, times=(0.01,), size=(1, 1))
    code, stderr = _cli("calibrate-noise", *files, "--crf", "srgb", "-o", tmp_path / "n.json")
    assert code == 1 and "holds 1 pixels, too few" in stderr and "black" not in stderr, stderr


@needs_shared
def test_given_times_that_contradict_the_frames_are_named(tmp_path):
    """Equal times given to a 4-stop bracket, and a wrong given time (1/60 s for a 1/125 s
    frame) with a response model that does not fit either (gamma 1.5, checked against the
    bracket's own fit): the messages name --times and the frame, not the metadata or the
    response alone."""
    frames = sorted((SHARED / "brackets" / "stack_jpg").glob("stack_room_exp_[234].jpg"))
    code, stderr = _cli("merge", *frames, "--times", "0.1,0.1,0.1", "-o", tmp_path / "a.exr")
    assert code == 0 and "by --times" in stderr and "check --times" in stderr and "metadata" not in stderr, stderr
    code, stderr = _cli("merge", *frames, "--times", "0.125,0.0333,0.0166", "--crf", "gamma:1.5", "-o",
                        tmp_path / "b.exr")
    assert code == 0 and "stack_room_exp_4.jpg: labelled 1/60.24 s by --times" in stderr, stderr
    assert "not at fault" not in stderr and "metadata" not in stderr, stderr


@needs_shared
def test_two_frames_whose_labels_disagree_name_both(tmp_path):
    """Two frames tell a ratio, not which label is wrong: both are named, the absurd one
    included whichever is the reference."""
    frames = sorted((SHARED / "brackets" / "stack_jpg").glob("stack_room_exp_[23].jpg"))
    code, stderr = _cli("merge", *frames, "--times", "1e5,0.0333", "--crf", "srgb", "-o", tmp_path / "m.exr")
    assert code == 0 and "cannot tell which label is wrong" in stderr, stderr
    assert all(str(f) in stderr for f in frames) and "1e+05 s" in stderr


def test_unlit_flats_with_darks_blame_the_flats(tmp_path, flats_and_darks):
    """Dark frames given as --flats beside real darks: the flats are named, not the darks."""
    line = _refused(*_cli("calibrate-noise", "--flats", flats_and_darks / "darks", "--darks",
                          flats_and_darks / "darks", "-o", tmp_path / "out.json"), 1, ["not a flat field", "--flats"])
    assert "not a dark frame" not in line
    _nothing_written(tmp_path)


@pytest.mark.parametrize("command", ["calibrate-noise", "estimate-crf"])
def test_a_plot_is_not_left_behind_when_its_profile_cannot_be_written(tmp_path, jpeg_bracket, monkeypatch, command):
    """The profile and its plot are one transaction: a profile that fails to write takes
    the plot with it."""
    def fail(prof, path):
        def write(tmp):
            raise OSError(28, "No space left on device", tmp)
        return write

    for module in ("hdrmerge_cli.pipeline.calibrate", "hdrmerge_cli.pipeline.response"):
        monkeypatch.setattr(f"{module}.profile_writer", fail)
    folder, meta = jpeg_bracket
    args = ["--crf", "srgb"] if command == "calibrate-noise" else []
    _refused(*_cli(command, *frames_of(folder, meta), *args, "-o", tmp_path / "out.json", "--plot",
                   tmp_path / "out.png"), 1, [str(tmp_path / "out.json"), "No space left"])
    assert not list(tmp_path.iterdir())


def _with_alpha(src, dst, associated: bool):
    """The frames of ``src`` (8-bit) with an alpha channel: 128 on the left third, 0 on a
    band, 255 elsewhere; straight as PNG and unassociated TIFF store it, or multiplied in
    (associated TIFF)."""
    import OpenImageIO as oiio

    dst.mkdir()
    out_paths = []
    for p in sorted(src.glob("frame_*.png")):
        inp = oiio.ImageInput.open(str(p))
        spec, px = inp.spec(), inp.read_image(format=oiio.UINT8)
        inp.close()
        a = np.full(px.shape[:2], 255, np.uint8)
        a[:, :64], a[:, 64:80] = 128, 0
        colour = np.rint(px * (a[..., None] / 255.0)).astype(np.uint8) if associated else px
        new = oiio.ImageSpec(spec.width, spec.height, 4, oiio.UINT8)
        new.alpha_channel = 3
        for attr in spec.extra_attribs:
            new.attribute(attr.name, attr.type, attr.value)
        if not associated:
            new.attribute("oiio:UnassociatedAlpha", 1)
        q = dst / (p.stem + (".tif" if associated else ".png"))
        out = oiio.ImageOutput.create(str(q))
        assert out.open(str(q), new) and out.write_image(np.dstack([colour, a]))
        out.close()
        out_paths.append(q)
    return out_paths


@pytest.mark.parametrize("associated", [False, True])
def test_partial_alpha_is_a_weight_and_the_output_keeps_its_own(tmp_path, associated):
    """RGBA frames whose alpha is partial: the colour is read as the file declares it
    (straight in PNG; multiplied in, in an associated TIFF), alpha weighs the readings, and
    the EXR carries A with the colour multiplied by it (OpenEXR's convention): un-multiplied,
    it is the merge of the frames without alpha."""
    import OpenImageIO as oiio

    _cli("simulate", "-q", "-o", tmp_path / "rgb", "--format", "png", "--size", "192x128", "--frames", "3",
         "--seed", "2")
    rgba = _with_alpha(tmp_path / "rgb", tmp_path / "rgba", associated)
    for name, frames in (("ref", sorted((tmp_path / "rgb").glob("frame_*.png"))), ("alpha", rgba)):
        code, stderr = _cli("merge", *frames, "--crf", "srgb", "-o", tmp_path / f"{name}.exr")
        assert code == 0, stderr

    def read(path):
        inp = oiio.ImageInput.open(str(path))
        names, px = list(inp.spec().channelnames), inp.read_image(format=oiio.FLOAT)
        inp.close()
        return names, px

    (names, ref), (names_a, out) = read(tmp_path / "ref.exr"), read(tmp_path / "alpha.exr")
    assert names == ["R", "G", "B"] and names_a == ["R", "G", "B", "A"]
    alpha = out[..., 3]
    assert np.allclose(alpha[:, :64], 128 / 255) and np.all(alpha[:, 64:80] == 0) and np.all(alpha[:, 80:] == 1)
    straight = out[..., :3] / np.where(alpha > 0, alpha, 1)[..., None]
    tol = 0.02 if associated else 1e-3  # associated: the colour was rounded after multiplying by 1/2
    for part in (np.s_[:, :64], np.s_[:, 80:]):
        assert np.median(np.abs(straight[part] / ref[part] - 1)) < tol
    assert np.all(out[:, 64:80, :3] == 0)


def test_weights_lut_on_raw_gives_the_true_reason(tmp_path, dng_bracket):
    """A RAW bracket whose frames share their levels: weight tables are indexed by code
    value, and a RAW bracket is weighted from its noise model (merge --lut refuses it for
    the same reason)."""
    folder, meta = dng_bracket
    line = _refused(*_cli("weights-lut", *frames_of(folder, meta), "-o", tmp_path / "out.csv"), 1,
                    ["RAW mosaic", "noise model", "without --lut"], absent=["black levels"])
    assert ".dng" in line  # names the frame
    lut = tmp_path / "w.csv"
    assert _cli("weights-lut", "--times", "0.01,0.1", "--bits", "8", "-o", lut)[0] == 0
    _refused(*_cli("merge", *frames_of(folder, meta, [0, 1]), "--lut", lut, "-o", tmp_path / "m.exr"), 1,
             ["RAW mosaic", "noise model"])


@pytest.mark.parametrize("half", [False, True])
def test_a_valid_response_no_reference_can_fit_is_named_not_the_reference(tmp_path, jpeg_bracket, half):
    """A monotone, non-negative response table that puts every code below white under
    1e-41 of full scale: no --reference brings the merge into the EXR's range, so the
    response is named."""
    z = np.arange(256)
    values = np.where(z < 255, 1e-44 * (1 + z), 1.0)
    table = tmp_path / "odd.csv"
    table.write_text("z,linear\n" + "".join(f"{k},{v:.6g}\n" for k, v in zip(z, values)))
    line = _refused(*_cli("merge", *frames_of(*jpeg_bracket), "--crf", table, "-o", tmp_path / "out.exr",
                          *(["--half"] if half else [])), 1, ["camera response", "at any --reference"])
    assert "use a longer --reference" not in line
    _nothing_written(tmp_path)
