from glob import glob

from setuptools import setup

PACKAGE_NAME = 'sensor_sim'

setup(
    name=PACKAGE_NAME,
    version='0.1.0',
    packages=[PACKAGE_NAME],
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE_NAME]),
        ('share/' + PACKAGE_NAME, ['package.xml']),
        ('share/' + PACKAGE_NAME + '/params', glob('params/*')),
        ('share/' + PACKAGE_NAME + '/scenarios', glob('scenarios/*')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'sensor_sim = sensor_sim.sensor_sim_node:main',
        ]
    },
)
