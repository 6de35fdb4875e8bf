from glob import glob

from setuptools import find_packages, setup

package_name = 'psl_optimizer'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    package_data={package_name: []},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='psl developers',
    maintainer_email='psl@example.com',
    description='Reward evaluation, policy search (CMA-ES) and the learning loop of psl.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'reward_evaluator = psl_optimizer.reward_evaluator_node:main',
            'learner = psl_optimizer.learner_node:main',
        ],
    },
)
