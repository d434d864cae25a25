"""Trial data: the data model and its Parquet storage, the synthetic human–human generator and
the importers of the authors' recordings."""
