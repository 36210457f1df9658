"""ament_python build script: installs the package, its share/ files and executables."""
import re
from glob import glob
from pathlib import Path

from setuptools import find_packages, setup

package_name = 'stars_ros'
HERE = Path(__file__).resolve().parent
version = re.search(r'<version>([^<]+)</version>', (HERE / 'package.xml').read_text()).group(1)


def requirements(path: Path) -> list:
    """The pins of a requirements file: its lines less comments and blank lines, the files
    it includes (``-r other.txt``) followed."""
    pins = []
    for line in path.read_text().splitlines():
        pin = line.split('#', 1)[0].strip()
        if pin.startswith('-r '):
            pins += requirements(path.parent / pin[3:].strip())
        elif pin:
            pins.append(pin)
    return pins


# Installed into share/stars_ros/config: what the installed package and its docs name (the
# launch file's ranker.yaml, the packaged model's settings, the front door's quick start, the
# SROS2 policy); the evaluation's and the other backbones' configs are read from a checkout.
SHIPPED_CONFIGS = ['config/ranker.yaml', 'config/socnav1_gat.yaml', 'config/quickstart.yaml']


setup(
    name=package_name,
    version=version,
    packages=find_packages(include=[package_name, package_name + '.*']),  # offline_training: run from the checkout
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', SHIPPED_CONFIGS),
        ('share/' + package_name + '/config/security', glob('config/security/*.xml')),
        ('share/' + package_name + '/msg_schemas', glob('msg_schemas/*.json')),
        ('share/' + package_name + '/launch', glob('launch/*.py')),
        ('share/' + package_name + '/models', glob('models/*.pt') + glob('models/*.md')),
    ],
    package_data={package_name: ['hri/page/*']},  # the feedback page's HTML, CSS and script
    # serving graph checkpoints; training, evaluation, the peers, plots and tabular serving: [train]
    install_requires=['setuptools', *requirements(HERE / 'requirements.txt')],
    extras_require={'train': requirements(HERE / 'requirements-train.txt')},
    zip_safe=True,
    maintainer='stars_ros maintainers',
    maintainer_email='maintainers@stars-ros.dev',
    description='StARS personalised ranking of socially appropriate robot actions for ROS 2.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'ranker = stars_ros.ros.ranker:main',
            'managed_ranker = stars_ros.ros.managed_ranker:main',
            'scene_publisher = stars_ros.ros.scene_publisher:main',
            'replay = stars_ros.ros.replay:main',
            'sign_feedback = stars_ros.sign_feedback:main',
            'recording = stars_ros.recording.__main__:main',
            'hri_bridge = stars_ros.ros.hri_bridge:main',
            'hri_world = stars_ros.ros.hri_world:main',
            'feedback_page = stars_ros.ros.feedback_page:main',
        ],
    },
)
