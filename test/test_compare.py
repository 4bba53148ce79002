"""``suit-ros compare``: checkpoints and variants on validation drives, paired differences."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from suit_ros.compare import VARIANTS, pairs_of


def test_pairs_follow_the_documented_directions():
    runs = dict.fromkeys(('single', 'suit', 'single, tracking', 'suit, tracking',
                          'suit, memory dropped', 'suit, bfloat16', 'suit, overhead',
                          'suit, overhead, overhang keep', 'suit, tracking, box fit faces'))
    pairs = pairs_of(['single', 'suit'], runs, list(VARIANTS))
    assert ('suit', 'single') in pairs                                  # against the first
    assert ('suit', 'suit, memory dropped') in pairs                    # what the memory is worth
    assert ('suit, bfloat16', 'suit') in pairs                          # variant minus run
    assert ('single, tracking', 'single') in pairs
    assert ('suit, tracking', 'single, tracking') in pairs              # same variant, both
    # a variant of a variant against that variant: the same drives, the same tracker
    assert ('suit, overhead, overhang keep', 'suit, overhead') in pairs
    assert ('suit, tracking, box fit faces', 'suit, tracking') in pairs
    assert ('suit, tracking, box fit faces', 'suit') not in pairs
    assert not any('zero displacement' in a or 'zero displacement' in b for a, b in pairs)


@pytest.mark.slow
def test_compare_command_writes_paired_results(tmp_path):
    from suit_ros.checkpoint import default_checkpoint_path
    shipped = default_checkpoint_path()
    out = tmp_path / 'cmp'
    single = shipped.parent / 'centerpoint_single.safetensors'
    cmd = [sys.executable, '-m', 'suit_ros.cli', 'compare', '--run', 'a', str(shipped),
           '--run', 'b', str(shipped), '--run', 's', str(single),
           '--variant', 'memory dropped', '--variant', 'tracking',
           '--drives', '2', '--frames', '4', '--resamples', '20', '--threads', '1',
           '--cache-dir', str(tmp_path / 'cache'), '--out', str(out)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    data = json.loads((out / 'results.json').read_text())
    # the single-frame model has no memory to drop
    assert set(data['runs']) == {'a', 'b', 'a, memory dropped', 'b, memory dropped',
                                 'a, tracking', 'b, tracking', 's', 's, tracking'}
    value, low, high = data['differences']['s - a']['mAP']
    assert low <= value <= high
    same = data['differences']['b - a']['mAP']
    assert same == [0.0, 0.0, 0.0]                 # one checkpoint twice: no difference
    assert 'a - a, memory dropped' in data['differences']
    assert '## Paired differences' in (out / 'results.md').read_text()
    # the page renders again from its JSON, figure for figure (a change of the page alone
    # needs no new runs)
    from suit_ros.compare import read, render
    assert render(read(out / 'results.json'), 'Checkpoint comparison',
                  'suit-ros compare ...') == (out / 'results.md').read_text()
    bad = subprocess.run(cmd[:4] + ['--out', str(out)], capture_output=True, text=True)
    assert bad.returncode != 0 and 'give checkpoints' in bad.stderr
    missing = subprocess.run(cmd[:4] + ['--run', 'x', str(tmp_path / 'nope.safetensors'),
                                        '--out', str(out)], capture_output=True, text=True)
    assert missing.returncode != 0 and 'does not exist' in missing.stderr


def test_a_ground_variant_runs_only_where_it_changes_the_input():
    """``ground local`` runs a checkpoint that asks for its input as given, ``ground as
    given`` one that asks for it leveled (the shipped ones); otherwise no run (None)."""
    from suit_ros.compare import variant_run
    from suit_ros.config import model_config_from_dict
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.model.detector import SUITDetector
    drives = [s[:2] for s in synthetic_split('tune', 1, 2)]
    for trained, applies in (('local', 'ground as given'), ('as_given', 'ground local')):
        cfg = model_config_from_dict({'temporal': 'none', 'pillars': {'ground': trained}},
                                     'test')
        model = SUITDetector(cfg).eval()
        other = 'ground local' if applies == 'ground as given' else 'ground as given'
        assert variant_run('unused', model, other, drives, 'float32') is None
        out = variant_run('unused', model, applies, drives, 'float32')
        assert out is not None and out.evaluate(cfg.class_names) is not None


def test_an_overhang_variant_runs_only_where_it_changes_the_input():
    """``overhang keep`` runs a checkpoint that drops the returns that hang (the shipped SUIT
    model), ``overhang drop`` one that keeps them; with ``overhead,`` the same on the drives
    with canopies; otherwise no run (None)."""
    from suit_ros.compare import variant_run
    from suit_ros.config import model_config_from_dict
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.model.detector import SUITDetector
    drives = [s[:2] for s in synthetic_split('tune', 1, 2)]
    for trained, applies in (('drop', 'keep'), ('keep', 'drop')):
        cfg = model_config_from_dict({'temporal': 'none', 'pillars': {'overhang': trained}},
                                     'test')
        model = SUITDetector(cfg).eval()
        for prefix in ('', 'overhead, '):
            assert variant_run('unused', model, f'{prefix}overhang {trained}', drives,
                               'float32') is None
            out = variant_run('unused', model, f'{prefix}overhang {applies}', drives, 'float32')
            assert out is not None and out.evaluate(cfg.class_names) is not None


def test_the_real_car_ends_variant_runs_the_same_drives_with_real_car_ends():
    """``real car ends``: the validation drives (the same seeds, routes and objects) with
    half the cars shaped at their ends as real cars are (``all car ends``: every car;
    ``street objects``: every car, and the street objects on the sidewalks; ``dark tops``: and
    half the cars seen only below the belt);
    ``tracking, ...`` the same tracked; all scored against the same boxes as the drives they
    replace."""
    from suit_ros.compare import variant_run
    from suit_ros.config import model_config_from_dict
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.model.detector import SUITDetector
    drives = synthetic_split('val', 1, 2)
    cfg = model_config_from_dict({'temporal': 'none'}, 'test')
    model = SUITDetector(cfg).eval()
    plain = variant_run('unused', model, 'tracking', drives, 'float32')
    for variant in ('real car ends', 'tracking, real car ends', 'all car ends',
                    'tracking, all car ends', 'street objects', 'tracking, street objects',
                    'dark tops', 'tracking, dark tops'):
        out = variant_run('unused', model, variant, drives, 'float32')
        assert out is not None and len(out.gt) == len(plain.gt) == 2
        for a, b in zip(out.gt, plain.gt):
            assert np.array_equal(a.boxes, b.boxes) and np.array_equal(a.labels, b.labels)
    shaped = synthetic_split('val', 1, 2, preset_name='val-ends')
    assert not np.array_equal(shaped[0][0].points, drives[0][0].points)
    every = synthetic_split('val', 1, 2, preset_name='val-ends-all')
    assert not np.array_equal(every[0][0].points, shaped[0][0].points)
    street = synthetic_split('val', 1, 2, preset_name='val-street-ends')
    assert len(street[0][0].points) != len(every[0][0].points)
    # bystanders: the street drives with some pedestrians moved, scored where they stand
    moved = variant_run('unused', model, 'tracking, bystanders', drives, 'float32')
    assert moved is not None and len(moved.gt) == 2
    by = synthetic_split('val', 1, 2, preset_name='val-bystanders')
    ped = cfg.class_names.index('pedestrian')
    assert not np.array_equal(by[0][0].gt.boxes[by[0][0].gt.labels == ped],
                              street[0][0].gt.boxes[street[0][0].gt.labels == ped])


def test_the_mirrored_variant_scores_the_mirrored_drives():
    """``mirrored``: the validation drives in left-hand traffic, scored against their own
    boxes mirrored; ``tracking, mirrored`` the same tracked."""
    from suit_ros.compare import variant_run
    from suit_ros.config import model_config_from_dict
    from suit_ros.data.sequences import synthetic_split
    from suit_ros.model.detector import SUITDetector
    drives = synthetic_split('val', 1, 2)
    cfg = model_config_from_dict({'temporal': 'none'}, 'test')
    model = SUITDetector(cfg).eval()
    plain = variant_run('unused', model, 'tracking', drives, 'float32')
    for variant in ('mirrored', 'tracking, mirrored'):
        out = variant_run('unused', model, variant, drives, 'float32')
        assert out is not None and len(out.gt) == 2
        # the model ran on the mirrored points: its boxes are not the plain drive's
        assert not np.array_equal(np.concatenate([d.boxes for d in out.det]),
                                  np.concatenate([d.boxes for d in plain.det]))
        for g, f in zip(out.gt, drives[0]):
            assert len(g.boxes) > 5
            assert np.allclose(g.boxes[:, 1], -f.gt.boxes[:, 1])
            assert np.allclose(np.cos(g.boxes[:, 6] + f.gt.boxes[:, 6]), 1.0)


def test_another_class_set_is_refused_before_any_drive_is_run(tmp_path):
    """A checkpoint of another class set (or a broken one) in second place is said before the
    first checkpoint's runs (an hour in --ablation), not after them."""
    from dataclasses import replace

    from suit_ros.checkpoint import save_checkpoint
    from suit_ros.cli import main
    from suit_ros.config import HeadConfig, ModelConfig
    from suit_ros.model.detector import SUITDetector
    cfg = replace(ModelConfig(), class_names=('car', 'pedestrian'),
                  head=replace(HeadConfig(), circle_nms_radius=(2.0, 0.5),
                               carry_nms_radius=(2.5, 1.0)))
    two = save_checkpoint(tmp_path / 'two.safetensors', SUITDetector(cfg), cfg)
    cache = tmp_path / 'cache'
    argv = ['compare', '--run', 'a', 'suit_default', '--run', 'b', str(two), '--drives', '2',
            '--frames', '2', '--cache-dir', str(cache), '--out', str(tmp_path / 'o')]
    assert main(argv) == 1
    assert not cache.exists()                    # no drive was made or run
    junk = tmp_path / 'junk.safetensors'
    junk.write_bytes(b'not a checkpoint' * 10)
    assert main(argv[:5] + [str(junk)] + argv[6:]) == 1
    assert not cache.exists()
