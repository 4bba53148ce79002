"""``detect-bag``: the node's parameter set, its flags, the /tf_static extrinsic, the summary."""
from __future__ import annotations

import argparse

import numpy as np
import pytest
from rosgraph import node_checkpoint, synthetic_bag

from suit_ros.detect_bag import configure_parser, params_from_args
from suit_ros.errors import BagError, ConfigError
from suit_ros.params import DetectorParams


def parse(*argv):
    parser = argparse.ArgumentParser()
    configure_parser(parser)
    return parser.parse_args(['in', 'out', *argv])


def test_flags_override_the_yaml_which_overrides_defaults(tmp_path):
    yaml = tmp_path / 'p.yaml'
    yaml.write_text('detector:\n  ros__parameters:\n    intensity_scale: 1.0\n'
                    '    max_range: 60.0\n')
    assert params_from_args(parse()) == DetectorParams()
    p = params_from_args(parse('--params', str(yaml), '--max-range', '40',
                               '--score-threshold', '0.3', '--extrinsic-xyz', '0', '0', '1.9',
                               '--extrinsic-rpy', '0', '0.1', '0', '--min-range', '2'))
    assert p.intensity_scale == 1.0 and p.max_range == 40.0 and p.min_range == 2.0
    assert p.score_thresholds == (0.3,) and p.extrinsic_xyz == (0.0, 0.0, 1.9)
    assert p.extrinsic_rpy == (0.0, 0.1, 0.0)
    assert p.precision == 'auto'
    assert params_from_args(parse('--precision', 'float32')).precision == 'float32'
    assert params_from_args(parse()).overhang == 'checkpoint'
    assert params_from_args(parse('--overhang', 'drop', '--ground', 'local')).overhang == 'drop'
    with pytest.raises(SystemExit):
        parse('--overhang', 'cut')
    assert params_from_args(parse()).box_fit == 'off'
    assert params_from_args(parse('--box-fit', 'faces')).box_fit == 'faces'
    with pytest.raises(SystemExit):
        parse('--box-fit', 'snap')
    with pytest.raises(SystemExit):
        parse('--precision', 'float16')
    with pytest.raises(ConfigError, match='min_range'):
        params_from_args(parse('--min-range', '50', '--max-range', '40'))


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    return synthetic_bag(tmp_path_factory.mktemp('bag'), 4, 11, 'mcap')


def test_extrinsic_from_tf_static_and_warning_summary(bag, tmp_path, capsys):
    from suit_ros.cli import main
    from suit_ros.data.bag import open_reader
    from suit_ros.data.sim import preset
    from suit_ros.data.sim.scene import Simulation
    from suit_ros.detect_bag import extrinsic_from_tf_static
    with open_reader(bag) as reader:
        xyz, rpy = extrinsic_from_tf_static(reader, 'base_link', 'lidar')
    T = Simulation(preset('test', frames=1), 11).T_base_lidar
    np.testing.assert_allclose(xyz, T[:3, 3], atol=1e-9)
    from suit_ros.ops.geometry import pose_from_xyz_rpy
    np.testing.assert_allclose(pose_from_xyz_rpy(xyz, rpy), T, atol=1e-9)
    with open_reader(bag) as reader, pytest.raises(BagError, match='no base_link -> os1'):
        extrinsic_from_tf_static(reader, 'base_link', 'os1')
    ckpt = node_checkpoint(tmp_path)
    # 0..255 intensities read as 0..1 reflectance: every frame flagged, and said so by reason
    assert main(['detect-bag', str(bag), str(tmp_path / 'out'), '--checkpoint', ckpt,
                 '--extrinsic-from-tf', '--intensity-scale', '1']) == 0
    out = capsys.readouterr().out
    assert f'extrinsic from /tf_static: xyz {[round(v, 4) for v in xyz]}' in out
    assert '4 warnings' in out
    assert 'warning intensity_range: 4 frames, e.g. intensity up to' in out
