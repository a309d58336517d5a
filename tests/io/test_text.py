"""Counts in user-facing text take the noun's number."""

from blurcalib.io.text import count


def test_count_takes_the_number_of_its_noun() -> None:
    assert count(1, "frame") == "1 frame"
    assert count(0, "frame") == "0 frames"
    assert count(34, "grid cell") == "34 grid cells"
    assert count(2, "analysis", "analyses") == "2 analyses"
