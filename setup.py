"""ament_python build of suit_ros (also a plain pip-installable package)."""
from glob import glob
import os

from setuptools import find_packages, setup

PACKAGE = 'suit_ros'

# ``msg_adapters`` lives at the repository root (the design card's layout) but installs as
# ``suit_ros.msg_adapters`` (through the symlink suit_ros/msg_adapters -> ../msg_adapters): a
# bare top-level ``msg_adapters`` would clash with any other package that picked the same
# generic name in a shared ROS install space or virtualenv.


def _data_files() -> list:
    files = [
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/params', sorted(glob('params/*.yaml'))),
        ('share/' + PACKAGE + '/dds', sorted(glob(PACKAGE + '/dds/*.xml'))),
    ]
    launch = sorted(glob('launch/*.py'))
    if launch:
        files.append(('share/' + PACKAGE + '/launch', launch))
    return files


def _version() -> str:
    with open(os.path.join(PACKAGE, '_version.py'), encoding='utf-8') as f:
        for line in f:
            if line.startswith('__version__'):
                return line.split('=')[1].strip().strip("'")
    raise RuntimeError('no __version__ in suit_ros/_version.py')


setup(
    name=PACKAGE,
    version=_version(),
    packages=find_packages(include=[PACKAGE, PACKAGE + '.*']),
    package_data={PACKAGE: ['checkpoints/*.safetensors', 'checkpoints/*.json',
                            'checkpoints/*.md', 'py.typed', 'dds/*.xml'],
                  PACKAGE + '.msg_adapters': ['py.typed']},
    data_files=_data_files(),
    install_requires=['setuptools', 'numpy', 'pyyaml'],
    zip_safe=False,
    maintainer='suit_ros maintainers',
    maintainer_email='suit-ros@example.com',
    description='SUIT multi-frame LiDAR 3D detector: ROS 2 node, bag tools, training',
    license='Apache-2.0',
    python_requires='>=3.10',
    entry_points={
        'console_scripts': [
            'detector = suit_ros.node:main',
            'suit-ros = suit_ros.cli:main',
        ],
    },
)
