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
    with pytest.raises(ConfigError, match='carry_s needs'):
        replace(ModelConfig(), sampling=SamplingConfig(carry_s=0.4))
    gated = replace(ModelConfig(), fusion_gate='unobserved')
    assert replace(gated, sampling=SamplingConfig(carry_s=0.4)).sampling.carry_s == 0.4
    for bad in (3.0, -0.1):
        with pytest.raises(ConfigError, match='carry_s must be within'):
            replace(gated, sampling=SamplingConfig(carry_s=bad))
    with pytest.raises(ConfigError, match='carry_s needs'):
        replace(gated, temporal='dense', sampling=SamplingConfig(carry_s=0.4))
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


def test_a_carry_counted_in_frames_is_read_in_seconds():
    """Configs and checkpoints from before the carry's lifetime was in seconds name
    ``sampling.carry_frames``: N frames read as (N + 0.5) x 0.1 s (the same N frames at the
    10 Hz the models were trained at, with room for jittered stamps; twice as many at 20 Hz);
    0 stays off; naming both, or a count that is not a whole number, is refused."""
    from suit_ros.config import model_config_from_dict
    from suit_ros.errors import ConfigError
    gated = {'fusion_gate': 'carry_branch'}
    assert model_config_from_dict({**gated, 'sampling': {'carry_frames': 8}}
                                  ).sampling.carry_s == 0.85
    assert model_config_from_dict({'sampling': {'carry_frames': 0, 'alpha': 0.2}}
                                  ).sampling == SamplingConfig(alpha=0.2)
    with pytest.raises(ConfigError, match='both given'):
        model_config_from_dict({**gated, 'sampling': {'carry_frames': 8, 'carry_s': 0.8}})
    for bad in (2.5, -1, True, '8'):
        with pytest.raises(ConfigError, match='whole number of frames'):
            model_config_from_dict({**gated, 'sampling': {'carry_frames': bad}})
    with pytest.raises(ConfigError, match='carry_s must be within'):
        model_config_from_dict({**gated, 'sampling': {'carry_frames': 30}})


def test_a_child_config_in_seconds_overrides_a_base_in_frames(tmp_path):
    """Each file's legacy carry is read before the merge, so a child's ``carry_s`` replaces
    its base's ``carry_frames`` (and the other way round), instead of both being given."""
    from suit_ros.config import load_model_config
    (tmp_path / 'base.yaml').write_text('fusion_gate: carry_branch\nsampling:\n'
                                        '  carry_frames: 8\n  alpha: 0.2\n')
    (tmp_path / 'child.yaml').write_text('_base_: base.yaml\nsampling:\n  carry_s: 1.2\n')
    (tmp_path / 'old.yaml').write_text('_base_: child.yaml\nsampling:\n  carry_frames: 3\n')
    child = load_model_config(tmp_path / 'child.yaml').sampling
    assert child.carry_s == 1.2 and child.alpha == 0.2
    assert load_model_config(tmp_path / 'old.yaml').sampling.carry_s == 0.35


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



def test_recipe_configs_load_and_match_the_shipped_checkpoints():
    """Every training config of the recipe (scripts/train_default.sh) loads with its model
    config, and the shipped checkpoints hold the config of their last stage (stage 10 for SUIT,
    stage 7 for the single-frame model), leveled to their local ground as they run (and SUIT's
    memory sampling at alpha 0.2)."""
    from dataclasses import replace

    from suit_ros.checkpoint import read_metadata
    from suit_ros.config import load_model_config, model_config_from_dict
    from suit_ros.train import load_train_config
    repo = Path(__file__).resolve().parents[1]
    recipe = (repo / 'scripts/train_default.sh').read_text()
    for path in sorted((repo / 'params').glob('train_*.yaml')):
        tc = load_train_config(path)
        load_model_config(repo / tc.model_config)
    for name, last in (('suit_default', 'train_suit_street_mix_cont.yaml'),
                       ('centerpoint_single', 'train_single_time10.yaml')):
        assert f'params/{last}' in recipe
        tc = load_train_config(repo / 'params' / last)
        stage = replace(load_model_config(repo / tc.model_config), temporal=tc.temporal)
        meta = read_metadata(repo / 'suit_ros/checkpoints' / f'{name}.safetensors')
        shipped = model_config_from_dict(meta['config'])
        assert shipped.pillars.ground == 'local'
        assert meta['extra']['train_config'].get('preset', '') == tc.preset, name
        # set after training, as the recipe does: leveled input; SUIT's memory sampling
        runtime = ['pillars.ground'] + (['sampling.alpha'] if name == 'suit_default' else [])
        assert sorted(shipped.diff(stage)) == sorted(runtime), (name, shipped.diff(stage))
        if name == 'suit_default':
            assert shipped.sampling.alpha == 0.2
