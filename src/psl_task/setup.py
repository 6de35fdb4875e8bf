"""ament_python package; metadata, executables and data files are in setup.cfg."""
from setuptools import setup

setup()
