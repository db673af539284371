"""polarshape.io.tables: numeric tables as text, byte for byte what Python's format writes."""

from __future__ import annotations

import numpy as np
import pytest

from polarshape.io.tables import table_text


def _python(table: np.ndarray, prefix: str, delimiters: list[str], decimals: int) -> bytes:
    """The reference: one ``format`` per number (what trimesh's array_to_string does)."""
    lines = []
    for row in table:
        cells = [f"{v:.{decimals}f}" if table.dtype.kind == "f" else f"{v}" for v in row]
        text = prefix + cells[0]
        for d, c in zip(delimiters, cells[1:]):
            text += d + c
        lines.append(text + "\n")
    return "".join(lines).encode()


#: ties of the 8-decimal rounding (dyadic values: k / 2^9 is exactly …5 in the 9th decimal), signed zeros,
#: values rounding to ±0, huge and non-finite values, carries (0.999999995 → 1.00000000)
_HARD = [0.0, -0.0, 1 / 512, -1 / 512, 3 / 512, 5e-9, -5e-9, 1.5e-8, 2.5e-8, -2.5e-8, 4e-10, -4e-10, 0.999999995,
         0.9999999950000001, 9.999999995, -99.999999995, 4.5e7, 9.99999999999e7, 1e20, -1e300, np.nan, np.inf,
         -np.inf, 123456.78901234, -0.5, 0.5]


@pytest.mark.parametrize("decimals", [0, 1, 3, 8, 12])
def test_floats_are_what_python_formats(decimals: int) -> None:
    rng = np.random.default_rng(0)
    values = np.concatenate([rng.normal(size=3000), rng.normal(size=600) * 1e6, rng.normal(size=600) * 1e-9,
                             rng.integers(-2**20, 2**20, 3000) / 2.0 ** rng.integers(1, 30, 3000), _HARD])
    table = values[: len(values) // 3 * 3].reshape(-1, 3)
    assert table_text(table, prefix=b"v ", decimals=decimals) == _python(table, "v ", [" ", " "], decimals)


def test_integers_and_delimiters() -> None:
    rng = np.random.default_rng(1)
    table = rng.integers(-10**12, 10**12, size=(500, 6))
    table[0] = [0, 1, -1, 9, 10, -100]
    delimiters = [b"//", b" ", b"//", b" ", b"//"]
    assert table_text(table, prefix=b"f ", delimiters=delimiters) == _python(
        table, "f ", [d.decode() for d in delimiters], 8)
    assert table_text(np.array([7, 42], dtype=np.uint16)) == b"7\n42\n"  # one column


def test_empty_and_invalid() -> None:
    assert table_text(np.zeros((0, 3))) == b""
    with pytest.raises(ValueError, match="delimiters"):
        table_text(np.zeros((2, 3)), delimiters=[b" "])
    with pytest.raises(ValueError, match="integers or floats"):
        table_text(np.array([["a"]]))
    with pytest.raises(ValueError, match="decimals"):
        table_text(np.zeros((1, 1)), decimals=19)
