"""The colcon install layout that `ros2 run` / `ros2 launch` rely on, and the CLI basics."""
from __future__ import annotations

import os
from pathlib import Path
import subprocess
import sys

import pytest
from rosgraph import Probe, start_node, stop

# a colcon build and installed executables in separate processes: outside the fast unit loop
pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope='module')
def install(tmp_path_factory):
    work = tmp_path_factory.mktemp('colcon')
    colcon = Path(sys.executable).parent / 'colcon'
    env = dict(os.environ)
    env['PATH'] = f'{Path(sys.executable).parent}:{env["PATH"]}'
    proc = subprocess.run([str(colcon), 'build', '--base-paths', str(REPO), '--build-base',
                           str(work / 'build'), '--install-base', str(work / 'install'),
                           '--packages-select', 'suit_ros'], cwd=work, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return work / 'install' / 'suit_ros'


def site_packages(install: Path) -> Path:
    return next((install / 'lib').glob('python3*/site-packages'))


def test_install_layout(install):
    for exe in ('detector', 'suit-ros'):
        path = install / 'lib' / 'suit_ros' / exe
        assert path.is_file() and os.access(path, os.X_OK), exe
    assert (install / 'share/ament_index/resource_index/packages/suit_ros').is_file()
    assert (install / 'share/suit_ros/package.xml').read_text().count('<name>suit_ros') == 1
    installed = {p.name for p in (install / 'share/suit_ros/params').glob('*.yaml')}
    assert installed == {p.name for p in (REPO / 'params').glob('*.yaml')}
    assert (install / 'share/suit_ros/launch/detector.launch.py').is_file()
    assert (install / 'share/suit_ros/dds/fastdds_large_data.xml').is_file()
    sp = site_packages(install)
    adapters = sp / 'suit_ros' / 'msg_adapters'
    assert adapters.is_dir() and not adapters.is_symlink()
    assert {p.name for p in adapters.glob('*.py')} == {p.name for p in
                                                       (REPO / 'msg_adapters').glob('*.py')}
    assert (adapters / 'py.typed').is_file()
    assert not (sp / 'msg_adapters').exists()                # no generic top-level package
    assert (sp / 'suit_ros' / 'checkpoints' / 'suit_default.safetensors').is_file()


def test_installed_cli_runs(install):
    from suit_ros import __version__
    exe = install / 'lib/suit_ros/suit-ros'
    shebang = exe.read_text().splitlines()[0]
    assert Path(shebang[2:]).parent == Path(sys.executable).parent        # the venv's python
    env = dict(os.environ, PYTHONPATH=str(site_packages(install)))
    out = subprocess.run([str(exe), '--version'], env=env, cwd=install, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == f'suit-ros {__version__}'
    where = subprocess.run(
        [sys.executable, '-c', 'import suit_ros.msg_adapters.pointcloud2 as m; print(m.__file__)'],
        env=env, cwd=install, capture_output=True, text=True, timeout=60)
    assert where.stdout.strip() == str(site_packages(install) / 'suit_ros/msg_adapters/'
                                       'pointcloud2.py')      # the install, not the checkout


def test_installed_detector_starts_and_publishes(install, tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray

    from suit_ros.checkpoint import save_checkpoint
    from suit_ros.config import ModelConfig
    from suit_ros.model.detector import SUITDetector
    ckpt = tmp_path / 'm.safetensors'
    save_checkpoint(ckpt, SUITDetector(ModelConfig()), ModelConfig())
    os.environ['PYTHONPATH'] = str(site_packages(install))
    try:
        proc = start_node(str(ckpt), cmd=[sys.executable,
                                          str(install / 'lib/suit_ros/detector')])
    finally:
        del os.environ['PYTHONPATH']
    probe = Probe()
    seen = []
    probe.node.create_subscription(DiagnosticArray, '/diagnostics', seen.append, 10)
    try:
        # start-up (torch, the model, its full-size warm-up) took over 60 s once on 2 cores
        # shared with a training run and the other test worker
        assert probe.spin_until(lambda: bool(seen) or proc.poll() is not None, 180.0)
    finally:
        probe.close()
        out = stop(proc)
    assert seen, out
    assert str(install) in out           # the node ran from the install tree


def test_cli_version_info_and_errors(capsys):
    from suit_ros.cli import main
    with pytest.raises(SystemExit):
        main(['--version'])
    assert 'suit-ros 0.1.0' in capsys.readouterr().out
    assert main(['info']) == 0
    text = capsys.readouterr().out
    for key in ('python', 'numpy', 'torch', 'rclpy', 'rmw', 'torch threads', 'torch device'):
        assert key in text
    assert 'rmw_fastrtps_cpp' in text
    # an RMW that is not installed: said in its line, and the rest still reported
    import json
    import os
    import subprocess
    import sys
    env = {**os.environ, 'RMW_IMPLEMENTATION': 'rmw_not_installed_cpp'}
    done = subprocess.run([sys.executable, '-m', 'suit_ros.cli', 'info', '--json'],
                          capture_output=True, text=True, env=env, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    info = json.loads(done.stdout)
    assert info['rmw'].startswith('cannot load rmw_not_installed_cpp') and info['numpy']
    assert main([]) == 2
    assert main(['train', '--config', '/nonexistent.yaml', '--out', '/tmp/x']) == 1
    assert 'does not exist' in capsys.readouterr().err
