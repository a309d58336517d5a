"""Camera models: the parametric (Brown-Conrady) camera, the central generic camera and their files."""
