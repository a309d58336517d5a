"""Running many frames: the process and thread runtime, and the Dask cluster."""
