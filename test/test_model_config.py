"""Model configs: validation, YAML base and overrides."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from suit_ros.config import ModelConfig, PillarConfig, SamplingConfig


def test_config_validation():
    from suit_ros.errors import ConfigError
    with pytest.raises(ConfigError, match='temporal'):
        ModelConfig(temporal='lstm')
    with pytest.raises(ConfigError, match='alpha'):
        replace(ModelConfig(), sampling=SamplingConfig(alpha=1.5))
    with pytest.raises(ConfigError, match='time_scale'):
        replace(ModelConfig(), pillars=PillarConfig(time_scale=0.0))
    # the carry needs the gate (it keeps samples only where the input has no returns)
    with pytest.raises(ConfigError, match='carry_frames needs'):
        replace(ModelConfig(), sampling=SamplingConfig(carry_frames=4))
    gated = replace(ModelConfig(), fusion_gate='unobserved')
    assert replace(gated, sampling=SamplingConfig(carry_frames=4)).sampling.carry_frames == 4
    with pytest.raises(ConfigError, match='carry_frames must be within'):
        replace(gated, sampling=SamplingConfig(carry_frames=21))
    with pytest.raises(ConfigError, match='carry_frames needs'):
        replace(gated, temporal='dense', sampling=SamplingConfig(carry_frames=4))
    # retired experiment settings: accepted at their 'off' value (older checkpoints carry
    # them), refused otherwise with where to find the experiment
    from suit_ros.config import model_config_from_dict
    old = ModelConfig().to_dict()
    old['memory_stride'] = 1
    old['pillars']['time_channels'] = False
    assert model_config_from_dict(old) == ModelConfig()
    old['pillars']['time_channels'] = True
    with pytest.raises(ConfigError, match='time_channels.*44202bd'):
        model_config_from_dict(old)
    with pytest.raises(ConfigError, match='memory_stride'):
        model_config_from_dict({'memory_stride': 3})


def test_model_yaml_base_and_overrides(tmp_path):
    from suit_ros.config import load_model_config
    from suit_ros.errors import ConfigError
    repo = Path(__file__).resolve().parents[1]
    shipped = load_model_config(repo / 'params/model_cpu_time10.yaml')
    base = load_model_config(repo / 'params/model_cpu.yaml')
    assert shipped.pillars.time_scale == 10.0 and base.pillars.time_scale == 1.0
    assert shipped.diff(base) == ['pillars.time_scale']
    (tmp_path / 'a.yaml').write_text('_base_: b.yaml\nmodel:\n  sweeps: 2\n')
    (tmp_path / 'b.yaml').write_text('_base_: a.yaml\n')
    with pytest.raises(ConfigError, match='cycle'):
        load_model_config(tmp_path / 'a.yaml')

