"""What a user gets wrong on the command line is named, before any long run, with exit 1 and
no traceback: outputs that cannot be written, counts that make no sense, broken configs."""
from __future__ import annotations

import pytest

from suit_ros.cli import main


@pytest.fixture
def under_a_file(tmp_path):
    """A path whose parent is a file: nothing can be written there."""
    (tmp_path / 'file').write_text('x')
    return tmp_path / 'file' / 'out'


def run_cli(capsys, *argv):
    code = main(list(argv))
    err = capsys.readouterr().err
    assert 'Traceback' not in err
    return code, err


def test_outputs_are_checked_before_the_run(tmp_path, under_a_file, capsys):
    checks = [
        (['eval', '--synthetic', 'val', '--json-out', str(under_a_file / 'm.json')],
         '--json-out file'),
        (['eval', '--synthetic', 'val', '--plot', str(tmp_path)], 'is a folder: give a file'),
        (['report', '--kitti', str(tmp_path), '--out', str(under_a_file)], '--out folder'),
        (['compare', '--run', 'a', 'suit_default', '--out', str(under_a_file)],
         '--out folder'),
        (['outage', '--markdown', str(under_a_file / 't.md')], '--markdown file'),
        (['train', '--config', 'params/train_suit.yaml', '--out', str(under_a_file)],
         '--out folder'),
    ]
    for argv, message in checks:
        code, err = run_cli(capsys, *argv)
        assert code == 1 and message in err, (argv, err)


def test_counts_that_make_no_sense_are_refused(tmp_path, capsys):
    for argv, message in (
            (['eval', '--synthetic', 'val', '--history', '0'], '--history must be at least 1'),
            (['choose-thresholds', '--drives', '0'], '--drives must be at least 1'),
            (['choose-thresholds', '--checkpoint', 'suit_default', '--keep-published'],
             'has no carry branch'),
            (['play', str(tmp_path / 'bag'), '--start-delay', '-1'],
             '--start-delay and --wait-subscribers are seconds >= 0'),
            (['play', str(tmp_path / 'bag'), '--start-delay', 'nan'],
             '--start-delay and --wait-subscribers are seconds >= 0'),
            (['play', str(tmp_path / 'bag'), '--rate', 'nan'], '--rate must be a number > 0'),
            (['play', str(tmp_path / 'bag'), '--max-messages', '-1'],
             '--max-messages is a count >= 0'),
            (['train', '--config', 'params/train_suit.yaml', '--out', str(tmp_path / 't'),
              '--steps', '0'], 'steps must be at least 1')):
        code, err = run_cli(capsys, *argv)
        assert code == 1 and message in err, (argv, err)


def test_keeping_published_thresholds_a_checkpoint_lacks_is_refused(tmp_path, capsys):
    """A carry branch fine-tuned by `suit-ros train` has no published thresholds: keeping
    them would keep the decoding threshold (0.1) and choose carry thresholds for it."""
    import shutil

    from safetensors.torch import load_file

    from suit_ros.checkpoint import _write, read_metadata, resolve_checkpoint
    src = resolve_checkpoint('suit_carry')
    meta = {k: v for k, v in read_metadata(src).items() if k != 'publish_thresholds'}
    bare = tmp_path / 'trained.safetensors'
    shutil.copy(src, bare)
    _write(bare, load_file(str(src)), meta)
    code, err = run_cli(capsys, 'choose-thresholds', '--checkpoint', str(bare),
                        '--keep-published')
    assert code == 1 and 'has no published thresholds for car, truck, pedestrian, cyclist' \
        in err and 'copy them from the checkpoint it was trained from' in err


def test_a_broken_training_config_is_named(tmp_path, capsys):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('steps: [1, 2\n', encoding='utf-8')
    code, err = run_cli(capsys, 'train', '--config', str(bad), '--out', str(tmp_path / 'o'))
    assert code == 1 and 'is not valid YAML' in err
    negative = tmp_path / 'neg.yaml'
    negative.write_text('steps: -5\n', encoding='utf-8')
    code, err = run_cli(capsys, 'train', '--config', str(negative), '--out', str(tmp_path / 'o'))
    assert code == 1 and 'steps must be at least 1, not -5' in err


def test_a_bag_topic_of_another_type_is_named(tmp_path, capsys):
    from rosgraph import synthetic_bag
    bag = synthetic_bag(tmp_path / 'bag', 2, 11, 'sqlite3')
    code, err = run_cli(capsys, 'eval', '--bag', str(bag), '--det-topic', '/odom')
    assert code == 1 and '/odom carries nav_msgs/msg/Odometry, not sensor_msgs/msg/PointCloud2' \
        in err
    code, err = run_cli(capsys, 'eval', '--bag', str(bag), '--det-topic', '/nothing')
    assert code == 1 and 'the bag has no /nothing topic' in err and 'detect-bag' in err
    # flags that change nothing for detections already recorded are refused, not ignored
    code, err = run_cli(capsys, 'eval', '--bag', str(bag), '--checkpoint', 'suit_carry',
                        '--tracker')
    assert code == 1 and '--checkpoint, --tracker do not apply there' in err
    # play: a mistyped name among several topics is named, not dropped
    code, err = run_cli(capsys, 'play', str(bag), '--topics', '/points', '/odmo')
    assert code == 1 and 'has no /odmo (topics: [' in err and "'/odom'" in err
