"""Configuration, stage orchestration on dask, resumability and the `lightstage` command line."""
