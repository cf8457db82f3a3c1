from glob import glob

from setuptools import setup

PACKAGE_NAME = 'stereo_coding_node'

setup(
    name=PACKAGE_NAME,
    version='0.1.0',
    packages=[PACKAGE_NAME],
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE_NAME]),
        ('share/' + PACKAGE_NAME, ['package.xml']),
        ('share/' + PACKAGE_NAME + '/params', glob('params/*')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'stereo_coding_node = stereo_coding_node.encoder_node:main',
            'stereo_decoding_node = stereo_coding_node.decoder_node:main',
        ]
    },
)
