"""The data of the benchmark and its I/O: the sequence schema and files (`schema`, `sequence`, `storage`), their
digests (`digests`, and `scored`: what the metrics read), dataset directories (`manifest`), the named splits and
their pins (`splits`, `pins`), `validate` (+ `checks`), the authors' release (`official`) and real or simulated
captures (`capture`). `arraybytes` lies below storage and the digests; the modules import each other without a
cycle (tests/test_import_graph.py).

Imports with numpy and h5py alone.
"""
