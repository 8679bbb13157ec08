"""simulate renders each frame at its ISO (Hasinoff et al. 2010: the gain amplifies the
photo-electrons and the pre-amplifier read noise; the post-amplifier read noise is not
amplified); calibrate-noise recovers the parameters per ISO and the read-noise split."""
import json

import numpy as np
import pytest

from conftest import frames_of
from hdrmerge_cli.core.sensor import SensorModel
from hdrmerge_cli.io.frames import read_frame
from hdrmerge_cli.io.images import read_exr

#: the simulated sensor at ISO 100: pre-amplifier read noise (9 - 4) / 0.25 = 20 electrons^2
SENSOR = SensorModel(alpha=0.25, sigma_o2=9.0, sigma_post2=4.0, base_iso=100)
#: per ISO, three exposures 16 times apart around the middle of the built-in scene, at
#: ISO i shortened by the gain i / 100 (the same code values)
TIMES_AT_100 = (1 / 352, 1 / 22, 0.727)
ISOS = (100, 400, 1600)


def simulate(run, folder, *args):
    run("simulate", "-o", folder, "-q", *args)
    return json.loads((folder / "simulation.json").read_text())


@pytest.fixture(scope="module")
def iso_bracket(tmp_path_factory, run):
    """9 DNG frames of the built-in scene (256 x 192), three at each of ISO 100, 400, 1600,
    sigma_post2 = 4, calibrated by calibrate-noise."""
    folder = tmp_path_factory.mktemp("isos")
    times = [t * 100 / iso for iso in ISOS for t in TIMES_AT_100]
    isos = [iso for iso in ISOS for _ in TIMES_AT_100]
    meta = simulate(run, folder, "--size", "256x192", "--seed", "2", "--sigma-o2", "9", "--alpha", "0.25",
                    "--sigma-post2", "4", "--times", ",".join(f"{t:.6g}" for t in times),
                    "--iso", ",".join(map(str, isos)))
    summary = json.loads(run("calibrate-noise", *frames_of(folder, meta), "-o", folder / "n.json", "--json").stdout)
    return folder, meta, summary


def test_each_frame_states_its_iso_and_the_sensor_at_it(iso_bracket):
    folder, meta, _ = iso_bracket
    assert sorted(meta["isos"]) == sorted(iso for iso in ISOS for _ in TIMES_AT_100) and meta["iso"] is None
    h = np.array(meta["exposure_times"]) * meta["isos"]
    assert np.all(np.diff(h) >= 0)  # merge's order, shortest exposure first
    for name, t, iso in zip(meta["frames"], meta["exposure_times"], meta["isos"]):
        f = read_frame(folder / name)
        assert f.iso == iso and f.exposure_time == pytest.approx(t, rel=1e-5)
    assert set(meta["sensor_at_iso"]) == {"ISO100", "ISO400", "ISO1600"}
    for iso in ISOS:
        assert meta["sensor_at_iso"][f"ISO{iso}"] == SENSOR.at_iso(iso).as_dict() | {"bits": 14, "black": 512}


def test_calibrate_noise_recovers_each_iso(iso_bracket):
    """Per ISO and channel, sigma_o2 and alpha from the exposure pairs within 4 of their
    reported standard errors of at_iso's (sigma_o2 with quantisation's 1/12); those errors
    at most 10 % of alpha and 5 % of sigma_o2 (about 4-9 % and 2.5-5 % on these 256 x 192
    frames 16 times apart; over seeds 1-7 the largest deviation was 2.4 errors)."""
    _, meta, summary = iso_bracket
    assert set(summary["noise"]) == {"ISO100", "ISO400", "ISO1600"}
    for iso in ISOS:
        truth = SENSOR.at_iso(iso)
        for ch, e in summary["noise"][f"ISO{iso}"].items():
            se = e["stderr"]
            assert e["method"]["alpha"] == e["method"]["sigma_o2"] == "exposure pairs", (iso, ch)
            assert abs(e["alpha"] - truth.alpha) < 4 * se["alpha"] and se["alpha"] < 0.10 * truth.alpha, (iso, ch)
            assert abs(e["sigma_o2"] - truth.sigma_o2_total) < 4 * se["sigma_o2"], (iso, ch)
            assert se["sigma_o2"] < 0.05 * truth.sigma_o2_total, (iso, ch)


def test_calibrate_noise_splits_the_read_noise_across_isos(iso_bracket):
    """sigma_o2(ISO) = pre alpha(ISO) + post: pre = 20 electrons^2, post = 4 + 1/12 (the
    quantisation is after the amplifier), each within 4 of its reported standard error
    (about 1.2 and 0.55 here; over seeds 1-7 the largest deviation was 2.6 errors)."""
    folder, _, summary = iso_bracket
    split = summary["read_noise_split"]
    assert split == json.loads((folder / "n.json").read_text())["read_noise_split"]
    assert set(split) == {"R", "G", "B", "G2"}
    for ch, e in split.items():
        se = e["stderr"]
        assert e["isos"] == list(ISOS) and e["weighted"]
        assert abs(e["pre_amp_electrons2"] - SENSOR.pre_amp_electrons2) < 4 * se["pre_amp_electrons2"], ch
        assert abs(e["post_amp_codes2"] - (4 + 1 / 12)) < 4 * se["post_amp_codes2"], ch
        assert se["pre_amp_electrons2"] < 0.1 * SENSOR.pre_amp_electrons2


def test_one_iso_gives_no_split(run, tmp_path, iso_bracket):
    folder, meta, _ = iso_bracket
    one = [folder / n for n, iso in zip(meta["frames"], meta["isos"]) if iso == 400]
    s = json.loads(run("calibrate-noise", *one, "-o", tmp_path / "n.json", "--json").stdout)
    assert s["read_noise_split"] is None and "read_noise_split" not in json.loads((tmp_path / "n.json").read_text())


def test_truth_of_a_mixed_iso_bracket_is_in_the_units_of_merge(run, tmp_path):
    """Frames at ISO 400, 100, 1600, 400: merge divides each by h = t ISO / ISO of its first
    frame and scales to the geometric mean of h; the truth states that reference (exposure
    and ISO) and agrees with the merged mosaic where the truth lies between 1 % and 50 % of
    full scale: median ratio within 1 % (0.05 % measured; a wrong ISO scaling is a factor
    of 4), RMS log ratio below 0.05 (0.03 measured, the noise of these frames)."""
    folder = tmp_path / "b"
    meta = simulate(run, folder, "--size", "128x96", "--seed", "4", "--times", "1/2000,1/500,1/500,1/125",
                    "--iso", "400,100,1600,400", "--sigma-post2", "4")
    assert meta["isos"] == [400, 100, 1600, 400] and meta["reference_iso"] == 400
    h = np.array(meta["exposure_times"]) * np.array(meta["isos"]) / 400
    assert meta["reference_exposure"] == pytest.approx(np.exp(np.mean(np.log(h))), rel=1e-12)
    out = tmp_path / "m.exr"
    s = json.loads(run("merge", *frames_of(folder, meta), "--cfa", "-o", out, "--json").stdout)
    assert s["reference_exposure"] == pytest.approx(meta["reference_exposure"], rel=1e-6)
    est, _ = read_exr(out)
    from hdrmerge_cli.core.cfa import mosaic

    truth = mosaic(read_exr(folder / "truth.exr")[0], "RGGB")
    ok = (truth > 0.01) & (truth < 0.5) & (est[..., 0] > 0)
    ratio = est[..., 0][ok] / truth[ok]
    assert np.median(ratio) == pytest.approx(1.0, abs=0.01)
    assert np.sqrt(np.mean(np.log(ratio) ** 2)) < 0.05


def test_jpeg_frames_carry_their_iso(run, tmp_path):
    meta = simulate(run, tmp_path / "j", "--format", "jpg", "--size", "64x48", "--times", "0.01,0.01",
                    "--iso", "200,800", "--repeat", "2")
    assert meta["isos"] == [200, 200, 800, 800] and meta["exposure_times"] == pytest.approx([0.01] * 4, rel=1e-3)
    assert [read_frame(tmp_path / "j" / n).iso for n in meta["frames"]] == [200, 200, 800, 800]


def test_automatic_times_are_for_the_single_iso(run, tmp_path):
    """--iso 1600 (the sensor given at ISO 100) without --times: the sensor saturates 16 times sooner, the automatic
    times are 16 times shorter (to the rounding of photographic times to 1/n s, up to
    1 / (2 n): 5 % at 1/10 s) and the
    shortest frame keeps its highlights as at ISO 100."""
    base = simulate(run, tmp_path / "a", "--size", "128x96", "--frames", "3")
    high = simulate(run, tmp_path / "b", "--size", "128x96", "--frames", "3", "--iso", "1600",
                    "--base-iso", "100")
    np.testing.assert_allclose(np.array(base["exposure_times"]) / high["exposure_times"], 16, rtol=0.05)
    assert high["saturated_fraction"][0] < 0.01 and high["isos"] == [1600] * 3


@pytest.mark.parametrize("args,option,code", [
    (("--iso", "100,400"), "--iso", 2),
    (("--iso", "100,400", "--times", "0.01,0.02,0.04"), "--iso", 2),
    (("--iso", "100,0", "--times", "0.01,0.02"), "--iso", 2),
    (("--sigma-post2", "10", "--sigma-o2", "9"), "--sigma-post2", 2),
    (("--base-iso", "0"), "--base-iso", 2),
])
def test_bad_iso_options_are_one_line_usage_errors(run, tmp_path, args, option, code):
    proc = run("simulate", "-o", tmp_path / "s", "--size", "64x64", *args, check=False)
    assert proc.returncode == code and option in proc.stderr and "Traceback" not in proc.stderr
    assert len([ln for ln in proc.stderr.splitlines() if ln.startswith("Error")]) == 1
    assert not (tmp_path / "s").exists()


def test_the_api_refuses_a_list_without_times(tmp_path):
    from hdrmerge_cli.core.errors import HdrMergeError
    from hdrmerge_cli.pipeline.simulate import SimulateOptions, simulate as simulate_api

    with pytest.raises(HdrMergeError, match="--iso: a list of 2 ISOs"):
        simulate_api(SimulateOptions(output_dir=tmp_path / "s", width=64, height=64, iso=[100, 400]))
    with pytest.raises(HdrMergeError, match="--iso: 2 ISOs for 3 exposure times"):
        simulate_api(SimulateOptions(output_dir=tmp_path / "s", width=64, height=64, iso=[100, 400],
                                     times=[0.01, 0.02, 0.04]))


def test_without_base_iso_the_parameters_hold_at_the_lowest_iso(run, tmp_path):
    meta = simulate(run, tmp_path / "c", "--size", "64x64", "--frames", "2", "--iso", "400", "--alpha", "2")
    assert meta["sensor_at_iso"]["ISO400"]["alpha"] == pytest.approx(2.0)
