"""resume.py: a resumed run's config is the saved one; flags are checked against it field by field."""
import json

import pytest

from higher_dist.config import ConfigError
from higher_dist.config_presets import make_config
from higher_dist.resume import CHANGEABLE_ON_RESUME, record_resume, resume_config, saved_config


def test_no_flags_is_the_saved_run_unchanged():
    saved = make_config("her", "small", **{"dqn.lr": 0.002})
    cfg, changes = resume_config(saved, {})
    assert cfg == saved and changes == {}


def test_flags_that_repeat_the_run_pass_silently():
    saved = make_config("her", "small", seed=4)
    cfg, changes = resume_config(saved, {"preset": "her", "world": "small", "seed": 4, "dqn.lr": saved.dqn.lr})
    assert cfg == saved and changes == {}


def test_changeable_fields_are_applied_and_reported_with_both_values():
    saved = make_config("higher", "small")
    cfg, changes = resume_config(saved, {"frames": 999_999, "actors": 3, "torch_threads": 2})
    assert (cfg.frames, cfg.actors, cfg.torch_threads) == (999_999, 3, 2)
    assert changes == {"frames": [saved.frames, 999_999], "actors": [saved.actors, 3], "torch_threads": [0, 2]}
    assert cfg.dqn == saved.dqn and cfg.preset == "higher"


@pytest.mark.parametrize("key, value", [("dqn.lr", 0.1), ("seed", 7), ("network.conv_channels", [8]),
                                        ("exploration.eps_base", 0.3), ("envs_per_actor", 3)])
def test_any_other_change_is_refused_naming_the_field_and_both_values(key, value):
    saved = make_config("her", "small")
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")) as e:
        resume_config(saved, {key: value})
    assert "config.json" in str(e.value) and json.dumps(value) in str(e.value)
    assert key not in CHANGEABLE_ON_RESUME


def test_a_bad_value_is_refused_as_without_resume():
    with pytest.raises(ConfigError, match="frames"):
        resume_config(make_config("her", "small"), {"frames": 0})


def test_the_saved_config_is_read_from_the_run_and_each_resume_is_recorded(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        saved_config(tmp_path)
    (tmp_path / "config.json").write_text("{not json")
    with pytest.raises(ConfigError, match="cannot read"):
        saved_config(tmp_path)
    cfg = make_config("dqn", "small")
    (tmp_path / "config.json").write_text(cfg.to_json())
    assert saved_config(tmp_path) == cfg
    record_resume(tmp_path, {"frames": [1, 2]}, argv=["higher-cluster", "--resume"])
    record_resume(tmp_path, {}, argv=["x"])
    lines = [json.loads(line) for line in (tmp_path / "history.jsonl").read_text().splitlines()]
    assert [line["changes"] for line in lines] == [{"frames": [1, 2]}, {}]
    assert lines[0]["argv"] == ["higher-cluster", "--resume"]
