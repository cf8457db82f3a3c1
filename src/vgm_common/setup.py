from glob import glob

from setuptools import setup

PACKAGE_NAME = 'vgm_common'

setup(
    name=PACKAGE_NAME,
    version='0.1.0',
    packages=[PACKAGE_NAME],
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE_NAME]),
        ('share/' + PACKAGE_NAME, ['package.xml']),
        ('share/' + PACKAGE_NAME + '/urdf', glob('urdf/*')),
        ('share/' + PACKAGE_NAME + '/params', glob('params/*')),
        ('share/' + PACKAGE_NAME + '/config', glob('config/*')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'vgm_launch = vgm_common.launcher:main',
        ]
    },
)
