"""4x HDR downscale, per-view streaming statistics, segmentation and flare scores."""
