"""Reading and writing chamber runs (docs/log-format.md): MCAP and Parquet layouts, block codecs, shared checks,
schemas."""
