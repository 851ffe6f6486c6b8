"""dsr-bench: the dataset and benchmark toolkit for 3D dynamic scene representations (DSR).

The library imports with numpy and h5py alone; torch, pybullet, open3d and rerun are imported
lazily by the modules that need them.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("dsr-bench")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.3.0"
