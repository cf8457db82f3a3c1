from setuptools import setup

PACKAGE_NAME = 'bag_tools'

setup(
    name=PACKAGE_NAME,
    version='0.1.0',
    packages=[PACKAGE_NAME],
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE_NAME]),
        ('share/' + PACKAGE_NAME, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'recorder = bag_tools.recorder_node:main',
            'player = bag_tools.player_node:main',
            'reindex = bag_tools.reindex:main',
        ]
    },
)
