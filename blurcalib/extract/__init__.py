"""Feature extraction from one frame, its noise model, local alignment and quality filtering."""
