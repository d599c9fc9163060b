"""Camera intrinsics and poses (pycolmap), turntable registration, world light positions, exports."""
