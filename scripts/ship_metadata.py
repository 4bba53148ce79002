#!/usr/bin/env python3
"""Set a trained SUIT checkpoint's metadata as it ships: input leveled to the local ground,
memory sampling alpha 0.2 (docs/experiments/memory_size), and a description.

Usage: scripts/ship_metadata.py CHECKPOINT DESCRIPTION
"""
import sys

from suit_ros.checkpoint import read_metadata, update_metadata

path, description = sys.argv[1], sys.argv[2]
config = read_metadata(path)['config']
config['pillars']['ground'] = 'local'
config['sampling']['alpha'] = 0.2
update_metadata(path, config=config, description=description)
