"""The data of the benchmark and its I/O: the sequence schema and files (`schema`, `sequence`), their
digests (`digests`), dataset directories (`manifest`), the named splits and their pins (`splits`,
`pins`), `validate`, the authors' release (`official`) and real or simulated captures (`capture`).

Imports with numpy and h5py alone.
"""
