"""Pure processing stages on numpy arrays: no Prefect, no zarr, no file paths."""
