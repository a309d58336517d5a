"""The whole pipeline over many frames, its thread policy and its Dask scale-out."""
