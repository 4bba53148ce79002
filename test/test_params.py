"""DetectorParams: one owner of the node's settings (defaults, YAML, validation)."""
from __future__ import annotations

from dataclasses import replace

import pytest
from rosgraph import REPO

from suit_ros.errors import ConfigError
from suit_ros.params import DetectorParams, render_markdown, render_yaml, runtime_parameters


def test_params_yaml_is_generated_from_the_dataclass():
    # regenerate with: python -m suit_ros.params > params/detector.yaml
    assert (REPO / 'params' / 'detector.yaml').read_text() == render_yaml()
    assert DetectorParams.from_yaml(str(REPO / 'params' / 'detector.yaml')) == DetectorParams()


def test_readme_parameter_table_is_generated_from_the_dataclass():
    # regenerate with: python -m suit_ros.params --markdown (between the markers)
    readme = (REPO / 'README.md').read_text()
    assert render_markdown() in readme
    for name in DetectorParams().ros_values():
        assert f'| `{name}` |' in render_markdown()


def test_readme_links_point_at_files():
    import re
    readme = (REPO / 'README.md').read_text()
    links = re.findall(r'\]\(([^)#]+)\)', readme)
    assert links and all((REPO / link).exists() for link in links), links


def test_a_renamed_parameter_fails_with_its_new_name():
    with pytest.raises(ConfigError, match='velocity_filter is now tracking'):
        DetectorParams().updated({'velocity_filter': True})
    with pytest.raises(ConfigError, match=r'coast_frames is now coast_s \(seconds'):
        DetectorParams().updated({'coast_frames': 5})


def test_yaml_values_override_defaults_and_unknown_keys_fail(tmp_path):
    path = tmp_path / 'p.yaml'
    path.write_text('detector:\n  ros__parameters:\n    intensity_scale: 1\n'
                    '    score_thresholds: [0.3]\n    points_qos: reliable\n')
    p = DetectorParams.from_yaml(str(path))
    assert p.intensity_scale == 1.0 and isinstance(p.intensity_scale, float)
    assert p.score_thresholds == (0.3,) and p.points_qos == 'reliable'
    path.write_text('detector:\n  ros__parameters:\n    max_time_gap: 1.0\n')
    with pytest.raises(ConfigError, match='unknown detector parameter'):
        DetectorParams.from_yaml(str(path))


@pytest.mark.parametrize('change,match', [
    ({'points_qos': 'fast'}, 'points_qos must be one of'),
    ({'device': 'tpu'}, 'device must be one of'),
    ({'extrinsic_xyz': (0.0, 1.0)}, 'extrinsic_xyz needs 3'),
    ({'extrinsic_rpy': (0.0, float('nan'), 0.0)}, 'extrinsic_rpy needs 3'),
    ({'min_range': 10.0, 'max_range': 5.0}, 'min_range'),
    ({'nms_iou_threshold': 1.5}, 'nms_iou_threshold must be within'),
    ({'score_thresholds': (0.2, 0.3)}, 'score_thresholds needs 1 or 4'),
    ({'score_thresholds': (1.2,)}, 'score_thresholds'),
    ({'odom_wait_s': -1.0}, 'odom_wait_s'),
])
def test_invalid_values_are_named(change, match):
    with pytest.raises(ConfigError, match=match):
        replace(DetectorParams(), **change).validate(num_classes=4)


def test_per_class_thresholds_pass_before_the_class_count_is_known(tmp_path):
    """detect-bag validates its flags before it loads the checkpoint: one threshold per class
    is taken then, and checked against the model's classes once they are known; a parameter
    file that cannot be read or parsed is named, not a traceback."""
    p = replace(DetectorParams(), score_thresholds=(0.3, 0.3, 0.2, 0.2))
    assert p.validate() is p and p.validate(num_classes=4) is p
    with pytest.raises(ConfigError, match='needs 1 or 3 values'):
        p.validate(num_classes=3)
    with pytest.raises(ConfigError, match='needs one or more values'):
        replace(DetectorParams(), score_thresholds=()).validate()
    with pytest.raises(ConfigError, match='cannot read the parameter file'):
        DetectorParams.from_yaml(str(tmp_path / 'missing.yaml'))
    with pytest.raises(ConfigError, match='cannot read the parameter file'):
        DetectorParams.from_yaml(str(tmp_path))
    bad = tmp_path / 'bad.yaml'
    bad.write_text('detector: [unclosed\n', encoding='utf-8')
    with pytest.raises(ConfigError, match='is not valid YAML'):
        DetectorParams.from_yaml(str(bad))


@pytest.mark.parametrize('values,match', [
    ({'max_detections': 2.5}, 'max_detections must be an integer'),
    ({'min_points': True}, 'min_points must be an integer'),
    ({'points_topic': 3}, 'points_topic must be a string'),
    ({'max_detections': float('inf')}, 'max_detections must be an integer'),   # YAML .inf
    ({'min_range': 'near'}, 'min_range must be a number'),
])
def test_wrong_types_are_refused(values, match):
    with pytest.raises(ConfigError, match=match):
        DetectorParams().updated(values)


def test_read_only_and_runtime_sets():
    runtime = set(runtime_parameters())
    assert {'checkpoint', 'device', 'threads', 'points_topic', 'odom_topic', 'points_qos',
            'diagnostics_period_s'}.isdisjoint(runtime)
    assert {'odom_tolerance_s', 'max_gap_s', 'intensity_scale', 'score_thresholds'} <= runtime


def test_class_thresholds():
    assert DetectorParams().class_thresholds(4) is None
    assert DetectorParams(score_thresholds=(0.3,)).class_thresholds(3) == [0.3, 0.3, 0.3]
    assert DetectorParams(score_thresholds=(0.1, 0.2)).class_thresholds(2) == [0.1, 0.2]


def test_large_data_profile_only_when_the_user_set_none():
    from xml.etree import ElementTree

    from suit_ros.dds import LARGE_DATA_PROFILE, use_large_data_profile
    env = {}
    assert use_large_data_profile(env) == str(LARGE_DATA_PROFILE)
    assert env == {'FASTRTPS_DEFAULT_PROFILES_FILE': str(LARGE_DATA_PROFILE)}
    for name in ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE'):
        env = {name: '/etc/mine.xml'}
        assert use_large_data_profile(env) is None and env == {name: '/etc/mine.xml'}
    ns = {'d': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
    root = ElementTree.parse(LARGE_DATA_PROFILE).getroot()
    shm = [t for t in root.iterfind('.//d:transport_descriptor', ns)
           if t.findtext('d:type', namespaces=ns) == 'SHM']
    assert int(shm[0].findtext('d:segment_size', namespaces=ns)) >= 32 * 2**20


def test_one_ros_environment_helper_keeps_dds_local():
    from suit_ros.rosenv import local_ros_env, shell_exports
    env = local_ros_env({'ROS_LOCALHOST_ONLY': '1', 'ROS_DOMAIN_ID': '7',
                         'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET'})
    assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST' and 'ROS_LOCALHOST_ONLY' not in env
    assert env['ROS_DOMAIN_ID'] == '7'
    fresh = local_ros_env({'ROS_DOMAIN_ID': '7'}, keep_domain=False)
    assert 1 <= int(fresh['ROS_DOMAIN_ID']) <= 100
    assert 'unset ROS_LOCALHOST_ONLY' in shell_exports()
    assert 'export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST' in shell_exports()
