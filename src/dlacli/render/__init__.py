"""Rendering: Gaussian splatting (CPU numba kernel, gsplat on CUDA) and triangle rasterisation."""
