from pathlib import Path

import pytest

from parammap.config import ConfigError, load_config, validate_config

ROOT = Path(__file__).resolve().parents[1]


def test_shipped_config_is_valid_and_defaults_fill():
    cfg = load_config(ROOT / "config" / "config.yaml")
    assert cfg["captures"] == {"demo": "data/captures/demo"}
    assert cfg["hdr"]["method"] == "debevec"
    assert validate_config({"captures": {"a": "x"}})["poses"]["max_rms_px"] == 2.0


@pytest.mark.parametrize(
    "cfg, key",
    [
        ({"captures": {"a": "x"}, "hdr": {"samples": 3}}, "hdr.samples"),
        ({"captures": {"a": "x"}, "hdr": {"method": "magic"}}, "hdr.method"),
        ({"captures": {}}, "captures"),
        ({"captures": {"a": "x"}, "workers": 0}, "workers"),
        ({"captures": {"a": "x"}, "typo_key": 1}, "<top>"),
        ({"captures": {"a": "x"}, "synth": {"a": {"preset": "huge"}}}, "synth.a.preset"),
    ],
)
def test_bad_values_name_the_key(cfg, key):
    with pytest.raises(ConfigError, match=f"config: {key}"):
        validate_config(cfg)


def test_schema_file_is_shared_with_workflow():
    wf = ROOT / "workflow" / "schemas" / "config.schema.yaml"
    pkg = ROOT / "src" / "parammap" / "schemas" / "config.schema.yaml"
    assert wf.resolve() == pkg.resolve()
