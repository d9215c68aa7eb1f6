"""Reading and writing chamber runs (log-format.md): MCAP and Parquet layouts, block codecs, shared checks, schemas."""
