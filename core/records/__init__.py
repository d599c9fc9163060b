"""Records that cross a stage boundary: calibration, processed frames, the shard format and its test index."""
