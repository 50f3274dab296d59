"""Pure processing stages on numpy arrays: no Prefect, no zarr, no file paths."""

# pymeshlab first, before Open3D and scipy.spatial load their own C++ runtimes: in the other order
# a Dask worker process that imported both corrupts its heap when it exits (glibc aborts with
# "malloc_consolidate(): unaligned fastbin chunk detected"; tests/flows/test_dask.py).
import pymeshlab  # noqa: F401  (isort: skip)
