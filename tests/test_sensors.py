"""Tests of the sensor section (gr_graph.sensors, cfg.sensor) and the renderer's beam models.

References: the datasheet numbers written out here by hand (VLP-16: +15..-15 deg every 2 deg,
0.2 deg azimuth steps at 10 Hz, 100 m; OS1-64: 64 beams evenly over +-22.5 deg; HDL-64E:
+2.0..-24.9 deg), the former closed form of the loop threshold ``0.35 * (64 / channels) ** 0.25``,
each rendered point's elevation recomputed from its coordinates, ring recovery from the
storage order of written files, and the route's ground truth.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from gr_graph.config import ConfigError, LoopConfig, SensorConfig, SlamConfig, config_to_yaml, load_config, loop_max_rmse
from gr_graph.datasets.base import DatasetError
from gr_graph.datasets.registry import KITTI_ROOT_ENV, open_sequence
from gr_graph.datasets.synthetic import SyntheticSequence
from gr_graph.datasets.synthetic.sensor import BeamModel
from gr_graph.sensors import (SENSOR_MODELS, SensorError, check_sequence_sensor, loop_rmse_threshold,
                              sensor_model)

VLP16_ELEVATIONS = [15, 13, 11, 9, 7, 5, 3, 1, -1, -3, -5, -7, -9, -11, -13, -15]  # VLP-16 datasheet


@pytest.fixture()
def synthetic_only(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """No KITTI root anywhere: open_sequence falls back to the synthetic sequence."""
    monkeypatch.delenv(KITTI_ROOT_ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HOME", str(tmp_path))


def _elevation_deg(points: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))


# ---------------------------------------------------------------- catalogue ---------------
def test_catalogue_matches_the_datasheets():
    vlp = sensor_model("vlp16")
    np.testing.assert_array_equal(vlp.elevations_deg, VLP16_ELEVATIONS)
    assert vlp.n_azimuth == round(360 / 0.2) and vlp.max_range == 100.0 and vlp.scan_period == 0.1
    os1 = sensor_model("OS1_64")  # case and _/- do not matter
    assert os1.name == "os1-64" and os1.n_beams == 64 and os1.n_azimuth in (1024, 2048)
    assert os1.vertical_fov_deg == pytest.approx((22.5, -22.5))
    np.testing.assert_allclose(np.diff(os1.elevations_deg), -45 / 63, atol=1e-12)  # uniform
    hdl = sensor_model("hdl64e")
    assert hdl.n_beams == 64 and hdl.vertical_fov_deg == pytest.approx((2.0, -24.9)) and hdl.n_azimuth == 2000
    for m in SENSOR_MODELS.values():
        assert np.all(np.diff(m.elevations_deg) < 0), f"{m.name}: ring 0 must be the highest beam"
    with pytest.raises(SensorError, match="known models: hdl64e, vlp16, os1-64"):
        sensor_model("hdl32e")


# ---------------------------------------------------------------- SensorConfig ------------
def test_sensor_config_fills_catalogue_models_and_checks_custom_ones():
    d = SensorConfig()
    assert (d.model, d.n_beams, d.has_ring, d.has_time, d.scan_period) == ("hdl64e", 64, None, None, None)
    v = SensorConfig(model="VLP16", has_time=True, time_unit="us", scan_period=0.05)
    assert (v.model, v.n_beams, v.vertical_fov_deg) == ("vlp16", 16, (15.0, -15.0))
    np.testing.assert_array_equal(v.beam_elevations_deg(), VLP16_ELEVATIONS)
    assert SensorConfig(model="vlp16", n_beams=16).n_beams == 16  # restating the model is fine
    with pytest.raises(ValueError, match="n_beams 32 contradicts model 'vlp16'.*model: custom"):
        SensorConfig(model="vlp16", n_beams=32)
    with pytest.raises(ValueError, match="unknown sensor model"):
        SensorConfig(model="pandar")
    c = SensorConfig(model="custom", n_beams=32, vertical_fov_deg=(10.0, -30.0))
    np.testing.assert_allclose(c.beam_elevations_deg(), np.linspace(10, -30, 32))
    e = SensorConfig(model="custom", n_beams=3, elevations_deg=(2.0, 0.0, -5.0))
    assert e.vertical_fov_deg == (2.0, -5.0) and e.fov_span_deg == 7.0
    with pytest.raises(ValueError, match="needs n_beams"):
        SensorConfig(model="custom", vertical_fov_deg=(10.0, -10.0))
    with pytest.raises(ValueError, match="needs elevations_deg or vertical_fov_deg"):
        SensorConfig(model="custom", n_beams=8)
    with pytest.raises(ValueError, match="strictly decreasing"):
        SensorConfig(model="custom", n_beams=3, elevations_deg=(0.0, 2.0, -5.0))
    with pytest.raises(ValueError, match="holds 2 beams"):
        SensorConfig(model="custom", n_beams=3, elevations_deg=(0.0, -5.0))


def test_channel_subsampling_only_for_64_beam_sensors():
    assert SensorConfig().effective_beams(None) == 64 and SensorConfig().effective_beams(16) == 16
    assert SensorConfig(model="os1-64").effective_beams(32) == 32
    vlp = SensorConfig(model="vlp16")
    assert vlp.effective_beams(None) == 16 and vlp.effective_beams(16) == 16  # all beams
    with pytest.raises(SensorError, match="applies to 64-beam sensors; sensor 'vlp16' has 16 beams"):
        vlp.effective_beams(32)
    # the same through the configuration: a ConfigError naming data.channels
    assert load_config(None, {"sensor": {"model": "vlp16"}}).channels == 16
    assert load_config(None, {"data": {"channels": 32}}).channels == 32
    with pytest.raises(ConfigError, match="data.channels.*64-beam sensors"):
        load_config(None, {"sensor": {"model": "vlp16"}, "data": {"channels": 32}})
    with pytest.raises(ConfigError, match="needs ring indices"):
        load_config(None, {"sensor": {"has_ring": False}, "data": {"channels": 16}})
    with pytest.raises(ConfigError, match="sensor.n_rings"):
        load_config(None, {"sensor": {"n_rings": 16}})  # unknown key, named with its section


def test_sensor_section_round_trips_through_yaml(tmp_path):
    cfg = load_config(None, {"sensor": {"model": "custom", "n_beams": 32, "vertical_fov_deg": [10.0, -30.0],
                                        "has_ring": True, "has_time": True, "time_unit": "ns",
                                        "time_reference": "absolute", "scan_period": 0.1}})
    text = config_to_yaml(cfg)
    assert yaml.safe_load(text)["sensor"]["time_unit"] == "ns"
    p = tmp_path / "c.yaml"
    p.write_text(text)
    assert load_config(p) == cfg
    # the default keeps a compact section: the catalogue's elevations are not written out
    assert "elevations_deg" not in yaml.safe_load(config_to_yaml(SlamConfig()))["sensor"]
    # only what was given is written: a rerun from the file guesses what the first run guessed
    # (the ring count from the data, not the default sensor's 64 beams; the time unit)
    assert yaml.safe_load(config_to_yaml(SlamConfig()))["sensor"] == {}
    p.write_text(config_to_yaml(SlamConfig()))
    again = load_config(p).sensor
    assert again.named_beams is None and again.time_unit is None and again == SlamConfig().sensor
    named = load_config(None, {"sensor": {"model": "vlp16"}})
    p.write_text(config_to_yaml(named))
    assert load_config(p).sensor.named_beams == 16


def test_cli_sensor_flag_replaces_the_beams_and_keeps_the_rest(tmp_path):
    from gr_graph.slam import build_parser, overrides_from_args

    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump({"sensor": {"model": "custom", "n_beams": 32, "vertical_fov_deg": [10.0, -30.0],
                                            "has_time": True, "time_unit": "ns"}}))
    args = build_parser().parse_args(["--sensor", "os1-64", "--config", str(p)])
    cfg = load_config(p, overrides_from_args(args))
    assert (cfg.sensor.model, cfg.sensor.n_beams, cfg.sensor.has_time, cfg.sensor.time_unit) == ("os1-64", 64, True, "ns")


# ---------------------------------------------------------------- thresholds --------------
def test_loop_threshold_follows_the_sensor():
    hdl, auto = SensorConfig(), LoopConfig()
    for ch in (None, 64, 32, 16):  # the HDL-64E keeps the former values exactly
        assert loop_max_rmse(auto, hdl, ch) == 0.35 * (64 / (ch or 64)) ** 0.25
    # other sensors: 0.35 m scaled by (vertical angle per ring / the HDL-64E's) ** 0.25
    vlp = loop_rmse_threshold(SensorConfig(model="vlp16"))
    assert vlp == pytest.approx(0.35 * ((30.0 / 16) / (26.9 / 64)) ** 0.25, rel=1e-12)
    os1 = loop_rmse_threshold(SensorConfig(model="os1-64"))
    assert os1 == pytest.approx(0.35 * ((45.0 / 64) / (26.9 / 64)) ** 0.25, rel=1e-12)
    os1_16 = loop_rmse_threshold(SensorConfig(model="os1-64"), 16)
    assert os1_16 == pytest.approx(0.35 * ((45.0 / 16) / (26.9 / 64)) ** 0.25, rel=1e-12)
    # sparser rings, larger threshold: OS1-64 (0.70 deg) < HDL 32 (0.84) < HDL 16 (1.68) < VLP-16 (1.875)
    assert 0.35 < os1 < loop_max_rmse(auto, hdl, 32) < loop_max_rmse(auto, hdl, 16) < vlp < os1_16
    # a custom sensor with the HDL-64E's field of view and 32 beams: the HDL's 32-channel value
    c32 = SensorConfig(model="custom", n_beams=32, vertical_fov_deg=(2.0, -24.9))
    assert loop_rmse_threshold(c32) == pytest.approx(loop_max_rmse(auto, hdl, 32), rel=1e-12)
    assert loop_max_rmse(LoopConfig(max_rmse=0.2), SensorConfig(model="vlp16")) == 0.2  # explicit wins


# ---------------------------------------------------------------- per-point times ---------
def test_times_to_fractions_units_and_references():
    ns = SensorConfig(model="os1-64", has_time=True, time_unit="ns", scan_period=0.1)
    np.testing.assert_allclose(ns.times_to_fractions(np.array([0, 25_000_000, 100_000_000], np.uint32)),
                               [0.0, 0.25, 1.0])
    # a partial sweep keeps its place in the sweep when times count from the sweep's start
    np.testing.assert_allclose(ns.times_to_fractions(np.array([50_000_000, 60_000_000])), [0.5, 0.6])
    end = SensorConfig(model="vlp16", time_unit="us", time_reference="sweep_end", scan_period=0.1)
    np.testing.assert_allclose(end.times_to_fractions(np.array([-100_000.0, -50_000.0, 0.0])), [0.0, 0.5, 1.0],
                               atol=1e-12)
    ab = SensorConfig(model="vlp16", time_unit="s", time_reference="absolute", scan_period=0.1)
    t = 1_700_000_000.0 + np.array([0.01, 0.05, 0.09])
    np.testing.assert_allclose(ab.times_to_fractions(t, sweep_start=1_700_000_000.0), [0.1, 0.5, 0.9], atol=1e-6)
    np.testing.assert_allclose(ab.times_to_fractions(t), [0.0, 0.4, 0.8], atol=1e-6)  # from the first point
    free = SensorConfig(model="vlp16", time_unit="ms")  # no scan period: stretched by the times' span
    np.testing.assert_allclose(free.times_to_fractions(np.array([3.0, 53.0, 103.0])), [0.0, 0.5, 1.0])
    wrong = SensorConfig(model="os1-64", time_unit="s", scan_period=0.1)  # nanoseconds read as seconds
    with pytest.raises(SensorError, match="check sensor.time_unit"):
        wrong.times_to_fractions(np.array([0.0, 5e7, 1e8]))
    with pytest.raises(SensorError, match="non-finite"):
        ns.times_to_fractions(np.array([0.0, np.nan]))


# ---------------------------------------------------------------- renderer ----------------
def test_beam_models_by_name():
    v = BeamModel(sensor="vlp16")
    assert (v.n_rings, v.n_beams, v.n_azimuth) == (16, 16, 1800)
    np.testing.assert_array_equal(v.elevations_deg, VLP16_ELEVATIONS)
    with pytest.raises(ValueError, match="n_rings must be 16"):
        BeamModel(n_rings=8, sensor="vlp16")
    o = BeamModel(n_rings=16, sensor="os1-64")
    np.testing.assert_allclose(o.elevations_deg, np.linspace(22.5, -22.5, 64)[::4])
    assert BeamModel() == BeamModel(n_rings=64, n_azimuth=2000, sensor="hdl64e")  # the default is unchanged
    with pytest.raises(SensorError):
        BeamModel(sensor="hdl32e")


def test_vlp16_render_rings_elevations_and_range():
    seq = SyntheticSequence(seed=0, sensor="vlp16", nthreads=1, preset="clean")
    assert seq.n_rings == 16 and seq.noise.max_range == 100.0 and seq.name == "synthetic-00-vlp16"
    assert (seq.sensor.model, seq.sensor.has_ring, seq.sensor.has_time) == ("vlp16", True, False)
    f = seq[200]
    assert f.n_rings == 16 and set(np.unique(f.ring)) == set(range(16))
    # every point lies on its ring's beam (the range noise is along the ray)
    np.testing.assert_allclose(_elevation_deg(f.points), np.asarray(VLP16_ELEVATIONS, float)[f.ring], atol=1e-6)
    r = np.linalg.norm(f.points, axis=1)
    assert r.max() <= 100.0 and np.all(np.diff(f.ring) >= 0)
    # azimuths on the 0.2 deg grid of the frame's phase, at most 1,800 per ring
    az = np.degrees(np.arctan2(f.points[:, 1], f.points[:, 0])) % 360.0
    steps = (az - az[0]) / 0.2
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)
    assert np.bincount(f.ring).max() <= 1800
    assert len(f) > 0.5 * 16 * 1800 * 0.5  # a town scene: most beams return (upper ones see the sky)


def test_os1_render_and_its_subsampled_rings():
    full = SyntheticSequence(seed=0, sensor="os1-64", nthreads=1, preset="clean")[300]  # seed 0: the town other tests build
    sub = SyntheticSequence(seed=0, sensor="os1-64", n_rings=16, nthreads=1, preset="clean")[300]
    el = np.linspace(22.5, -22.5, 64)
    np.testing.assert_allclose(_elevation_deg(full.points), el[full.ring], atol=1e-6)
    assert full.n_rings == 64 and sub.n_rings == 16
    keep = full.ring % 4 == 0  # a 16-ring render is exactly every 4th ring of the 64-ring one
    np.testing.assert_array_equal(sub.points, full.points[keep])
    np.testing.assert_array_equal(sub.ring, full.ring[keep] // 4)


def test_kitti_layout_export_of_a_vlp16_reads_back_with_its_rings(tmp_path, synthetic_only):
    """A VLP-16 export read as a KITTI-layout folder with ``sensor: vlp16``: the ring
    recovery of gr_graph.datasets.channels finds the rendered rings from the storage order."""
    from gr_graph.datasets.synthetic.writer import write_kitti_layout

    seq = SyntheticSequence(seed=0, sensor="vlp16", nthreads=1, preset="clean")
    write_kitti_layout(seq, tmp_path / "k", range(40, 43), progress=False)
    view, desc = open_sequence("00", data_root=tmp_path / "k", sensor="vlp16")
    assert "sensor vlp16 (16 beams)" in desc and "16 channels" in desc and view.sensor.model == "vlp16"
    for k in range(3):
        got, ref = view[k], seq[40 + k]
        np.testing.assert_allclose(got.points, ref.points, atol=1e-5)  # float32 files
        np.testing.assert_array_equal(got.ring, ref.ring)
    assert view.parent.ring_recovery_counts == {"storage_order": 3, "reference": 0, "line_rank": 0, "elevation": 0}
    with pytest.raises(DatasetError, match="64-beam sensors"):
        open_sequence("00", data_root=tmp_path / "k", sensor="vlp16", channels=32)


# ---------------------------------------------------------------- registry / pipeline ---
def test_open_sequence_renders_the_configured_sensor(synthetic_only):
    view, desc = open_sequence("00", frames="0:2", synthetic_preset="clean", sensor="vlp16")
    assert "sensor vlp16 (16 of 16 beams, 1800 azimuth steps)" in desc and desc.endswith("16 channels")
    assert view.sensor.model == "vlp16" and view[0].n_rings == 16
    with pytest.raises(DatasetError, match="applies to 64-beam sensors"):
        open_sequence("00", frames="0:2", synthetic_preset="clean", sensor="vlp16", channels=16 * 2)
    with pytest.raises(DatasetError, match="catalogue sensors only"):
        open_sequence("00", frames="0:2", synthetic_preset="clean",
                      sensor=SensorConfig(model="custom", n_beams=16, vertical_fov_deg=(15.0, -15.0)))
    # has_time: true on data without per-point times is refused, naming the frame
    needs_time, _ = open_sequence("00", frames="0:2", synthetic_preset="clean", sensor=SensorConfig(model="vlp16", has_time=True))
    with pytest.raises(DatasetError, match="frame 0: no per-point times"):
        needs_time[0]


def test_slam_refuses_a_sequence_of_another_sensor(synthetic_only):
    from gr_graph.frame_loop import run_slam

    view, _ = open_sequence("00", frames="0:3", synthetic_preset="clean", sensor="vlp16")
    check_sequence_sensor(view, SensorConfig(model="vlp16"))  # same sensor: fine
    with pytest.raises(SensorError, match="taken with sensor 'vlp16'.*configuration's sensor is 'hdl64e'.*--sensor vlp16"):
        run_slam(view, SlamConfig())


@pytest.mark.slow
def test_slam_on_a_vlp16_window_recovers_the_trajectory(tmp_path, synthetic_only):
    """``python -m gr_graph.slam --sensor vlp16`` on 80 rendered frames (76 m of street)."""
    from gr_graph.slam import main

    out = tmp_path / "run"
    assert main(["--sensor", "vlp16", "--synthetic-preset", "clean", "--frames", "0:80", "--no-loops", "--no-memory", "--no-progress",
                 "--out", str(out)]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["sensor"] == "vlp16" and m["channels"] == 16
    r0 = m["rounds"]["0"]
    assert r0["sensor"]["loop_max_rmse"] == pytest.approx(0.35 * ((30.0 / 16) / (26.9 / 64)) ** 0.25)
    assert r0["n_flagged_odometry_edges"] == 0
    # against the route's ground truth (independent of the renderer's output)
    est = np.loadtxt(out / "round_0" / "poses_tum.txt")[:, 1:4]
    gt = SyntheticSequence(seed=0).gt_poses[:80]
    gt_xyz = (np.linalg.inv(gt[0]) @ gt)[:, :3, 3]
    err = np.linalg.norm(est - gt_xyz, axis=1)
    path = np.sum(np.linalg.norm(np.diff(gt_xyz, axis=0), axis=1))
    assert path > 60 and err.max() < 0.01 * path, f"max error {err.max():.3f} m over {path:.0f} m"
    assert r0["slam"]["ate_rmse"] < 0.1


def test_config_yaml_of_earlier_versions_keeps_its_meaning():
    """A sensor section written out in full (every key, as config.yaml did before it kept only the
    given keys) at the defaults is read as unsaid: guessed from the data, as in the run that wrote
    it; and None (guessed) fingerprints like the former defaults, so finished rounds stay finished."""
    from gr_graph.pipeline import round_fingerprint
    from gr_graph.sensors import FORMER_FULL_DUMP_KEYS, SENSOR_MODELS

    full = {"model": "hdl64e", "n_beams": 64, "vertical_fov_deg": list(SENSOR_MODELS["hdl64e"].vertical_fov_deg),
            "elevations_deg": None, "has_ring": None, "has_time": None, "time_unit": "s",
            "time_reference": "sweep_start", "scan_period": None}
    assert set(full) == set(FORMER_FULL_DUMP_KEYS)
    old = load_config(None, {"sensor": full}).sensor
    assert old.named_beams is None and old.time_unit is None and old.time_reference is None
    assert old == SlamConfig().sensor
    vlp = load_config(None, {"sensor": {**full, "model": "vlp16", "n_beams": 16,
                                        "vertical_fov_deg": list(SENSOR_MODELS["vlp16"].vertical_fov_deg)}}).sensor
    assert vlp.named_beams == 16 and vlp.time_unit is None  # a named sensor stays named
    said = load_config(None, {"sensor": {"time_unit": "s"}}).sensor  # a key given alone is said
    assert said.time_unit == "s"
    for r in (0, 1):
        assert round_fingerprint(SlamConfig(), r) == round_fingerprint(
            load_config(None, {"sensor": {"time_unit": "s", "time_reference": "sweep_start"}}), r)
    assert round_fingerprint(SlamConfig(), 0) != round_fingerprint(load_config(None, {"sensor": {"time_unit": "ns"}}), 0)


def test_a_sensor_section_completed_by_the_command_line_keeps_what_it_says(tmp_path):
    """A config file giving has_ring, has_time, time_unit: s, time_reference: sweep_start and scan_period,
    with --sensor adding the other four keys, is no former full dump: its time unit and reference stay said."""
    from gr_graph import slam

    path = tmp_path / "c.yaml"
    path.write_text("sensor: {has_ring: null, has_time: null, time_unit: s, time_reference: sweep_start, "
                    "scan_period: null}\n")
    overrides = slam.overrides_from_args(slam.build_parser().parse_args(["--sensor", "vlp16"]))
    first = load_config(path, overrides)
    cfg = first.sensor
    assert cfg.model == "vlp16" and cfg.time_unit == "s" and cfg.time_reference == "sweep_start"
    # the run's config.yaml now lists all nine keys; a rerun from it alone still reads them as said
    from gr_graph.config import dump_config

    dump_config(first, tmp_path / "config.yaml")
    again = load_config(tmp_path / "config.yaml").sensor
    assert again.time_unit == "s" and again.time_reference == "sweep_start" and again == cfg
