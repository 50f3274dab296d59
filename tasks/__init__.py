"""Pure processing stages on numpy arrays: no Prefect, no zarr, no file paths."""

# pymeshlab first, before Open3D and scipy.spatial load their own C++ runtimes. With all three
# loaded, a process sometimes corrupts its heap when it exits, after its work is done (glibc aborts
# with "malloc_consolidate(): unaligned fastbin chunk detected"): measured in Dask worker processes,
# 3 of 18 exits in the other order, about 1 in 6 in this one. Not solved; loading pymeshlab only
# when meshing made the main process abort at exit instead.
import pymeshlab  # noqa: F401  (isort: skip)
