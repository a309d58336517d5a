"""Inputs and outputs: frames and videos, atomic writes, result tables and the reference tool's formats."""
