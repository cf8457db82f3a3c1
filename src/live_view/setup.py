from glob import glob

from setuptools import setup

PACKAGE_NAME = 'live_view'

setup(
    name=PACKAGE_NAME,
    version='0.1.0',
    packages=[PACKAGE_NAME],
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE_NAME]),
        ('share/' + PACKAGE_NAME, ['package.xml']),
        ('share/' + PACKAGE_NAME + '/layouts', glob('layouts/*')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    license='Apache-2.0',
    entry_points={'console_scripts': ['live_view = live_view.node:main']},
)
