"""Test-only helpers: synthetic work directories and shards, a synthetic sphere scene, tiny training configs."""
