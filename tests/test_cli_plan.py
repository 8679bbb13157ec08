"""hdrmerge-cli plan: end to end on simulated metering frames, outputs and bad input."""
import json

import numpy as np
import pytest

from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.io.profile import new_profile


@pytest.fixture(scope="module")
def metering(tmp_path_factory, run):
    """Three DNG metering frames of the built-in scene and a profile with three ISOs."""
    folder = tmp_path_factory.mktemp("meter")
    run("simulate", "-o", folder, "-q", "--size", "256x192", "--frames", "3", "--seed", "2")
    frames = sorted(folder.glob("frame_*.dng"))
    profile = folder / "camera.json"
    entries = {}
    for iso in (100, 400, 1600):
        g = iso / 100
        a = 0.25 * g * g
        entries[f"ISO{iso}"] = {ch: {"sigma_o2": 4 * a + 25.0, "alpha": a, "beta": 0.0} for ch in ("R", "G", "B")}
    prof = new_profile({"make": "hdrmerge-cli", "model": "simulated sensor"}, 14, CRF("linear"), [], "test")
    profile.write_text(json.dumps(prof | {"noise": entries}))
    return frames, profile


def test_plan_with_a_time_budget_prints_frames_and_json(run, metering):
    frames, profile = metering
    out = json.loads(run("plan", *frames, "--profile", profile, "--time", "0.25", "--json").stdout)
    assert out["frames"] and all(set(f) == {"time", "iso"} for f in out["frames"])
    assert sum(f["time"] for f in out["frames"]) <= 0.25 + 1e-9
    assert {f["iso"] for f in out["frames"]} <= {100.0, 400.0, 1600.0}
    compared = out["compared"]
    for name, other in compared.items():
        if other is not None and "same SNR" not in name:
            assert out["predicted_worst_snr_db"] >= other["predicted_worst_snr_db"] - 1e-6, name
    text = run("plan", *frames, "--profile", profile, "--time", "0.25").stdout
    assert "predicted worst-case SNR" in text and "conventional 1-EV bracket" in text


def test_min_snr_gives_the_shortest_plan_and_impossible_snr_is_one_line(run, metering):
    frames, profile = metering
    out = json.loads(run("plan", *frames, "--profile", profile, "--min-snr", "20", "--json").stdout)
    assert out["predicted_worst_snr_db"] >= 20 - 1e-6
    bad = run("plan", *frames, "--profile", profile, "--min-snr", "110", check=False)
    assert bad.returncode == 1 and "impossible" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1


def test_without_a_profile_plans_times_at_the_metering_iso(run, metering):
    frames, _ = metering
    out = json.loads(run("plan", *frames, "--time", "0.25", "--json").stdout)
    assert {f["iso"] for f in out["frames"]} == {100.0}
    bad = run("plan", *frames, "--time", "0.25", "--isos", "100,400", check=False)
    assert bad.returncode == 1 and "--isos" in bad.stderr


def test_gphoto2_script_and_plot(run, metering, tmp_path):
    frames, profile = metering
    script, plot = tmp_path / "shoot.sh", tmp_path / "snr.png"
    out = json.loads(run("plan", *frames, "--profile", profile, "--time", "0.1", "--gphoto2", script, "--plot", plot,
                         "--json").stdout)
    lines = [ln for ln in script.read_text().splitlines() if ln.startswith("gphoto2")]
    assert len(lines) == len(out["frames"])
    assert all("--capture-image-and-download" in ln and "shutterspeed=" in ln for ln in lines)
    assert plot.stat().st_size > 0
    again = run("plan", *frames, "--profile", profile, "--time", "0.1", "--gphoto2", script, check=False)
    assert again.returncode == 1 and "--overwrite" in again.stderr


def test_bad_input_is_refused_in_one_line(run, metering, tmp_path):
    frames, profile = metering
    short = run("plan", *frames, "--time", "0.00001", check=False)
    assert short.returncode == 1 and "shortest shutter time" in short.stderr
    assert run("plan", "--time", "1", check=False).returncode == 1
    assert run("plan", *frames, check=False).returncode == 2  # no objective
    missing = run("plan", *frames, "--profile", profile, "--time", "1", "--isos", "100,3200", check=False)
    assert missing.returncode == 1 and "ISO3200" in missing.stderr
    config = tmp_path / "plan.toml"
    config.write_text('[plan]\ntime = 0.1\nframes = 3\n')
    out = json.loads(run("plan", *frames, "--config", config, "--json").stdout)
    assert len(out["frames"]) <= 3 and out["total_time"] <= 0.1


def test_info_reports_the_bracket_snr_and_a_plan_of_the_same_time(run, metering):
    frames, profile = metering
    out = json.loads(run("info", *frames, "--snr", "--profile", profile, "--json").stdout)["snr"]
    own_time = out["total_time"]
    plan = out["plan_of_the_same_time"]
    assert sum(f["time"] for f in plan["frames"]) <= own_time * (1 + 1e-9)
    assert plan["predicted_worst_snr_db"] >= out["predicted_worst_snr_db"] - 1e-6
    text = run("info", *frames, "--snr").stdout
    assert "predicted worst-case SNR" in text
    assert run("info", *frames, "--profile", profile, check=False).returncode == 2  # --profile serves --snr


def test_one_shutter_speed_and_one_frame_still_give_a_table(run, metering):
    """A camera with one shutter time that cannot reach the brightest photosites: a
    warning, and the bands no frame measures print as '-'."""
    frames, _ = metering
    proc = run("plan", *frames, "--time", "1", "--frames", "1", "--shutter-speeds", "0.01")
    assert "1 frame," in proc.stdout and "clip even in the shortest frame" in proc.stderr
    out = json.loads(run("plan", *frames, "--time", "1", "--frames", "1", "--shutter-speeds", "0.01",
                         "--json").stdout)
    assert np.isfinite(out["predicted_worst_snr_db"]) and out["frames"] == [{"time": 0.01, "iso": 100.0}]


def test_a_plot_it_cannot_draw_is_refused_before_anything_is_written(run, metering, tmp_path):
    frames, profile = metering
    script = tmp_path / "shoot.sh"
    bad = run("plan", *frames, "--time", "0.1", "--gphoto2", script, "--plot", tmp_path / "snr.xyz", check=False)
    assert bad.returncode == 1 and "snr.xyz" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
    assert not script.exists() and not list(tmp_path.iterdir())


def test_the_raw_camera_sample_config_plans(run, metering):
    from pathlib import Path

    frames, profile = metering
    config = Path(__file__).resolve().parents[1] / "sample_configs" / "raw-camera.toml"
    out = json.loads(run("plan", *frames, "--config", config, "--profile", profile, "--time", "0.1", "--json").stdout)
    assert out["frames"] and out["worst_case"]["lose_dark"] == 1.0 and out["worst_case"]["lose_bright"] == 0.1
