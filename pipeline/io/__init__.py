"""File I/O for the library and the stages: atomic writes, checksummed zarr stores, parquet tables,
torch checkpoints, and `DataError` for a problem with an input file (knows no params.yaml or repo paths)."""
