"""Local deconvolution of star blocks (homography, PSF and brightness per block)."""
