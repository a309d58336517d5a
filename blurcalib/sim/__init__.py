"""The simulator of sharp and blurred frames and accuracy against its ground truth."""
