"""The raw-capture contract: stage description (stage.yaml), capture layout, the probe contract, and capture validation."""
