"""Point the ROS 2 wheels' CMake export files at this interpreter's include folders.

The wheels were built under /opt/python/cp311-cp311, and their exported targets name that
interpreter's include folder and its numpy include folder. Building an interface package
fails until both are rewritten to the local ones (../shared/DESIGN.md, section 6).
Usage: python fix_cmake_paths.py VENV
"""
import pathlib
import re
import sys
import sysconfig

import numpy

BUILDER = re.compile(r"/opt/python/cp311-cp311/(?:include/python3\.11|lib/python3\.11/site-packages/numpy/_core/include)")


def local_path(match: re.Match) -> str:
    if match.group(0).endswith("numpy/_core/include"):
        return numpy.get_include()
    return sysconfig.get_paths()["include"]


def main(venv: str) -> int:
    changed = 0
    for path in pathlib.Path(venv, "share").glob("*/cmake/*.cmake"):
        text = path.read_text()
        new = BUILDER.sub(local_path, text)
        if new != text:
            path.write_text(new)
            changed += 1
    print(f"[setup] rewrote include paths in {changed} CMake files")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
