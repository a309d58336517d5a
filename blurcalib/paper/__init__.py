"""Reproductions of the paper's experiments on simulated data (``blurcalib experiment ...``)."""
