"""Reading a CSV table with a header in chunks of rows, with one-line errors naming the file and row.

The file must be a regular file (:func:`blurcalib.io.input_file.open_input`); it is read as UTF-8
(a leading byte-order mark is skipped) and parsed as the ``csv`` module does, a chunk of rows at a
time, so that a reader converting each chunk to arrays never holds the whole file as strings.
Rows count from 1 after the header.
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Iterator, Sequence
from pathlib import Path

from blurcalib.io.input_file import InputFileError, open_input

CHUNK_ROWS = 65_536
"""Rows per chunk of :func:`csv_chunks`."""


def csv_chunks(path: str | os.PathLike[str], required: Sequence[str], error: type[Exception], what: str,
               optional: Sequence[str] = (), chunk_rows: int = CHUNK_ROWS
               ) -> Iterator[tuple[int, dict[str, list[str]]]]:
    """The ``required`` columns of a CSV with a header, and those of ``optional`` it has, as lists
    of strings, ``chunk_rows`` rows at a time.

    Args:
        path: the file.
        required: column names that must be in the header (others are ignored).
        error: the exception raised for a missing, unreadable or malformed file; its message starts
            with the path.
        what: what the file is, for the messages (``"results file"``, ``"calibration file"``).
        optional: column names read when the header has them.
        chunk_rows: rows per chunk.
    Yields:
        ``(first_row, columns)``: the number of the chunk's first row (from 1) and its columns.
        A file with a header and no rows yields one empty chunk.
    Raises:
        error: the file is missing, not a regular file, unreadable, not UTF-8, empty, lacks a
            required column, has a row with another number of fields than the header, or a
            field the ``csv`` module refuses (longer than its 131,072 characters).
    """
    p = Path(path)
    row = 0
    try:
        with open_input(p, what=what) as raw, io.TextIOWrapper(raw, encoding="utf-8-sig",
                                                               newline="") as text:
            reader = csv.reader(text)
            header = next(reader, None)
            if header is None:
                raise error(f"{p}: empty file (expected a header with columns {', '.join(required)})")
            missing = [c for c in required if c not in header]
            if missing:
                raise error(f"{p}: missing column(s) {', '.join(repr(c) for c in missing)}")
            wanted = [(name, header.index(name)) for name in (*required, *(o for o in optional
                                                                             if o in header))]
            chunk: list[list[str]] = []
            first = 1
            for fields in reader:
                row += 1
                if len(fields) != len(header):
                    raise error(f"{p}: row {row} (line {reader.line_num}) has {len(fields)} fields, "
                                f"expected {len(header)}")
                chunk.append(fields)
                if len(chunk) == chunk_rows:
                    yield first, {name: [r[i] for r in chunk] for name, i in wanted}
                    first, chunk = row + 1, []
            if chunk or row == 0:
                yield first, {name: [r[i] for r in chunk] for name, i in wanted}
    except FileNotFoundError:
        raise error(f"{p}: {what} not found") from None
    except InputFileError as exc:
        raise error(str(exc)) from None
    except UnicodeDecodeError:
        raise error(f"{p}: cannot read {what}: not UTF-8 text (after row {row})") from None
    except csv.Error as exc:
        problem = (f"a field longer than the {csv.field_size_limit()} characters a CSV field may have"
                   if "field limit" in str(exc) else str(exc))
        raise error(f"{p}: row {row + 1}: {problem}") from None
    except OSError as exc:
        raise error(f"{p}: cannot read {what} ({exc.strerror or exc})") from None
