"""The capture simulator: a producer of raw captures with ground truth (stage, scene, renderer, light probe), for
demos and tests. It writes the capture contract of `lightstage.capture` and is imported only by `pipelines/`,
benches and tests; no stage depends on it."""
