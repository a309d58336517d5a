"""The star calibration target: its pattern and its printable page."""
