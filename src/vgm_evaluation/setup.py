# The package is declared in setup.cfg (colcon runs this file).
from setuptools import setup

setup()
