"""The grouped settings: declarations, files, the former flat names, and a run repeated from its own folder."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from covo_gtsam.choices import MotionModel, OutlierRejection, RobustKernel, Weighting
from covo_gtsam.config import (
    FLAT_NAMES,
    GROUPS,
    EstimatorConfig,
    NoiseConfig,
    OdometryConfig,
    SensorConfig,
    TrackingConfig,
    load_config,
    save_config,
    settings_table,
)
from covo_gtsam.errors import ConfigError
from covo_gtsam.frontend import FrontendConfig
from covo_gtsam.validation import declared, range_text

DOCS = Path(__file__).resolve().parent.parent / "docs" / "configuration.md"


def _changed() -> OdometryConfig:
    """A configuration with a non-default value in every group, an enum, an unset optional set and inf."""
    return OdometryConfig(frontend=FrontendConfig(max_hamming=80, max_depth=math.inf, outlier_rejection="homography"),
                          noise=NoiseConfig(pixel_sigma=2.5), estimator=EstimatorConfig(robust="huber"),
                          sensor=SensorConfig(frame_interval_s=1 / 29.7), tracking=TrackingConfig(keyframes=True))


def test_every_setting_declares_unit_range_and_description():
    for name, cls in GROUPS.items():
        fields = declared(cls)
        assert [f.name for f in fields] == [f.name for f in dataclasses.fields(cls)], name  # nothing undeclared
        for f in fields:
            assert f.metadata["doc"] and "unit" in f.metadata and range_text(f), f"{name}.{f.name}"
    # the former flat names are exactly the settings outside the front end, each in one group
    assert set(FLAT_NAMES) == {f.name for g, cls in GROUPS.items() if g != "frontend" for f in declared(cls)}


def test_the_documentation_table_is_generated_from_the_declarations():
    text = DOCS.read_text(encoding="utf-8")
    table = re.search(r"<!-- settings table: .*? -->\n(.*?)<!-- end of the settings table -->", text, re.S).group(1)
    assert table == settings_table(), "regenerate docs/configuration.md's table: python -m covo_gtsam.config"
    assert settings_table().count("\n") == 2 + sum(len(declared(cls)) for cls in GROUPS.values())


def test_choices_are_strings_and_match_the_accepted_values():
    from covo_gtsam.estimator import ROBUST_KERNELS
    from covo_gtsam.frontend import OUTLIER_REJECTIONS
    from covo_gtsam.transfer import WEIGHTINGS

    assert tuple(Weighting) == WEIGHTINGS and (None, *RobustKernel) == ROBUST_KERNELS
    assert tuple(OutlierRejection) == OUTLIER_REJECTIONS
    assert tuple(MotionModel) == ("constant_velocity", "none")
    cfg = OdometryConfig.from_dict({"estimator": {"weighting": "thesis", "robust": "cauchy"},
                                    "tracking": {"motion_model": "none"}})
    assert cfg.estimator.weighting is Weighting.THESIS and cfg.estimator.weighting == "thesis"
    assert f"{cfg.estimator.weighting}" == "thesis" == str(cfg.estimator.weighting)
    assert json.dumps(cfg.estimator.robust) == '"cauchy"' and cfg.tracking.motion_model is MotionModel.NONE
    assert EstimatorConfig(weighting=Weighting.THESIS) == EstimatorConfig(weighting="thesis")
    for none in (None, "none", ""):  # TOML has no null
        assert EstimatorConfig(robust=none).robust is None


def test_groups_name_their_settings_in_errors():
    with pytest.raises(ConfigError, match=r"noise.pixel_sigma must be a positive number from 0.01 to 10000, got -1"):
        NoiseConfig(pixel_sigma=-1)
    with pytest.raises(ConfigError, match=r"unknown tracking.motion_model 'fast'; choose one of"):
        TrackingConfig(motion_model="fast")
    with pytest.raises(ConfigError, match="frontend.wta_k must be 2, 3 or 4"):
        FrontendConfig(wta_k=5)
    with pytest.raises(ConfigError, match="frontend.scale_factor must be a number > 1 and <= 2"):
        FrontendConfig(scale_factor=1.0)
    with pytest.raises(ConfigError, match="sensor must be a SensorConfig"):
        OdometryConfig(sensor=TrackingConfig())
    with pytest.raises(ConfigError, match="unknown configuration keys: noise.bogus, tracking.x"):
        OdometryConfig.from_dict({"noise": {"bogus": 1}, "tracking": {"x": 2}})
    with pytest.raises(ConfigError, match="unknown configuration group 'nois'"):
        OdometryConfig().replace(nois={"pixel_sigma": 1.0})


def test_replace_changes_settings_by_group():
    cfg = OdometryConfig().replace(sensor={"depth_scale": 1000.0}, tracking=TrackingConfig(restart_after=2))
    assert cfg.sensor.depth_scale == 1000.0 and cfg.sensor.frame_clock and cfg.tracking.restart_after == 2
    assert cfg.noise == NoiseConfig() and OdometryConfig().sensor.depth_scale == 5000.0
    assert dataclasses.replace(cfg, noise=NoiseConfig(pixel_sigma=3.0)).noise.pixel_sigma == 3.0


def test_flat_names_still_work_with_a_deprecation_warning():
    nested = OdometryConfig(noise=NoiseConfig(pixel_sigma=3.0), tracking=TrackingConfig(keyframes=True))
    with pytest.warns(DeprecationWarning, match=r"keyframes -> tracking.keyframes.*pixel_sigma -> noise.pixel_sigma"):
        assert OdometryConfig(pixel_sigma=3.0, keyframes=True) == nested
    with pytest.warns(DeprecationWarning, match="flat odometry settings"):
        assert OdometryConfig.from_dict({"pixel_sigma": 3.0, "keyframes": True}) == nested
    with pytest.warns(DeprecationWarning, match="flat odometry settings"):
        assert dataclasses.replace(OdometryConfig(), pixel_sigma=3.0).noise.pixel_sigma == 3.0
    with pytest.warns(DeprecationWarning, match=r"OdometryConfig.keyframes .* OdometryConfig.tracking.keyframes"):
        assert nested.keyframes is True
    with pytest.raises(AttributeError):
        nested.no_such_setting  # noqa: B018
    with pytest.raises(TypeError):
        OdometryConfig(no_such_setting=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        OdometryConfig.from_dict(OdometryConfig().to_dict())  # the nested form warns about nothing


@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_saved_configuration_loads_back_equal(tmp_path, suffix):
    cfg = _changed()
    path = save_config(cfg, tmp_path / f"c{suffix}", header="a test")
    assert load_config(path) == cfg
    assert load_config(save_config(OdometryConfig(), tmp_path / f"d{suffix}")) == OdometryConfig()
    numpy_valued = OdometryConfig(noise=NoiseConfig(pixel_sigma=np.float64(1.5)),
                                  tracking=TrackingConfig(restart_after=np.int64(3), keyframes=np.bool_(True)))
    assert load_config(save_config(numpy_valued, tmp_path / f"n{suffix}")) == numpy_valued
    with pytest.raises(ConfigError, match="is .toml or .json"):
        save_config(cfg, tmp_path / "c.yaml")


def test_a_file_with_flat_keys_loads_with_a_warning_naming_it(tmp_path):
    path = tmp_path / "old.json"
    path.write_text('{"pixel_sigma": 3.0, "frontend": {"n_features": 500}}')
    with pytest.warns(DeprecationWarning, match=r"old.json: flat odometry settings"):
        cfg = load_config(path)
    assert cfg.noise.pixel_sigma == 3.0 and cfg.frontend.n_features == 500
    from covo_gtsam.cli import load_config_file

    with pytest.warns(DeprecationWarning) as caught:  # the function's and the file's
        assert load_config_file(str(path)) == cfg
    assert any("use covo_gtsam.config.load_config" in str(w.message) for w in caught)


def test_cli_says_a_flat_file_is_deprecated_and_runs(sample_dir, tmp_path, capsys):
    from covo_gtsam.cli import main

    path = tmp_path / "old.toml"
    path.write_text("pixel_sigma = 3.0\n")
    assert main(["run", str(sample_dir), "--out", str(tmp_path / "o"), "--quiet", "--no-plots", "--max-frames", "3",
                 "--config", str(path)]) == 0
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("covo: warning: ") and "noise.pixel_sigma" in err[0]
    assert load_config(tmp_path / "o" / "config.toml").noise.pixel_sigma == 3.0


def test_a_run_is_repeated_from_its_own_folder(sample_dir, tmp_path):
    """covo run writes config.toml and the version; --config OUT/config.toml gives the same results,
    also when the first run's settings came from the command line."""
    from covo_gtsam import __version__
    from covo_gtsam.cli import main

    first, again = tmp_path / "first", tmp_path / "again"
    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps({"noise": {"pixel_sigma": 2.5}, "tracking": {"keyframes": True}}))
    common = ["--quiet", "--no-plots", "--max-frames", "14"]
    assert main(["run", str(sample_dir), "--out", str(first), "--config", str(cfg), "--weighting", "thesis",
                 *common]) == 0
    written = load_config(first / "config.toml")
    assert written.estimator.weighting == "thesis" and written.tracking.keyframes and written.noise.pixel_sigma == 2.5
    assert main(["run", str(sample_dir), "--out", str(again), "--config", str(first / "config.toml"), *common]) == 0
    for name in ("trajectory.txt", "relative.txt", "graph.g2o", "config.toml"):
        assert (again / name).read_bytes() == (first / name).read_bytes(), name

    def results(folder):
        m = json.loads((folder / "metrics.json").read_text())
        for timing in ("elapsed_s", "frames_per_second"):
            m.pop(timing)
        return m

    assert results(again) == results(first) and results(first)["version"] == __version__
