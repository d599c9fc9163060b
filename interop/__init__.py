"""Interop: exports that other tools open and public OLAT datasets in and out (docs/interop.md).

Readers and writers of external formats live here, after the dataset stage: the per-frame point-light format of
the NeRF / Gaussian-splatting relighting codes (`olat`), OpenIllumination (`openillumination`), and the work
directory they import into (`ingest`). They import the root package and capture, calibration, dataset only.
"""
