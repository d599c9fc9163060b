"""Train/test splits as data, scene bounds, and streaming ray shards for the trainer."""
