"""MERL binary BRDF files: layout, bit-exact round trip, errors naming the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from polarshape.errors import OutputExistsError
from polarshape.io.material import MaterialError
from polarshape.io.merl import MERL_CHANNEL_SCALE, MERL_SHAPE, MerlTable, read_merl, write_merl

N = 90 * 90 * 180


def random_table(seed: int = 0) -> MerlTable:
    rng = np.random.default_rng(seed)
    stored = rng.lognormal(0.0, 3.0, size=(3, *MERL_SHAPE))
    stored[rng.random(stored.shape) < 0.1] = -1.0  # missing samples
    stored[0, 0, 0, 0] = 0.0
    return MerlTable(stored)


def test_write_then_read_is_bit_exact(tmp_path: Path) -> None:
    table = random_table()
    path = write_merl(tmp_path / "t.binary", table)
    again = read_merl(path)
    assert again.stored.tobytes() == table.stored.tobytes()
    assert np.array_equal(again.valid, table.valid) and (~again.valid).sum() > 0
    write_merl(tmp_path / "u.binary", again)
    assert (tmp_path / "u.binary").read_bytes() == path.read_bytes()


def test_file_layout_header_channels_and_scale(tmp_path: Path) -> None:
    table = random_table(1)
    data = write_merl(tmp_path / "t.binary", table).read_bytes()
    assert len(data) == 12 + 3 * N * 8
    assert tuple(np.frombuffer(data, "<i4", count=3)) == (90, 90, 180)
    c, i, j, k = 1, 7, 33, 101  # green, θ_h 7, θ_d 33, φ_d 101
    offset = 12 + 8 * (c * N + k + 180 * (j + 90 * i))
    assert np.frombuffer(data, "<f8", count=1, offset=offset)[0] == table.stored[c, i, j, k]
    assert table.values[c, i, j, k] == pytest.approx(table.stored[c, i, j, k] * 1.15 / 1500, rel=1e-15)
    assert MERL_CHANNEL_SCALE == pytest.approx((1 / 1500, 1.15 / 1500, 1.66 / 1500))


def test_from_brdf_scales_and_marks_missing() -> None:
    values = np.full((3, *MERL_SHAPE), 0.25)
    values[2, 5, 5, 5] = np.nan
    values[0, 1, 1, 1] = -3.0
    table = MerlTable.from_brdf(values)
    assert table.stored[0, 0, 0, 0] == pytest.approx(0.25 * 1500)
    assert table.stored[2, 0, 0, 0] == pytest.approx(0.25 * 1500 / 1.66)
    assert not table.valid[2, 5, 5, 5] and not table.valid[0, 1, 1, 1] and table.valid.sum() == 3 * N - 2
    assert np.allclose(table.values[table.valid], 0.25, rtol=1e-14)
    mono = MerlTable.from_brdf(np.full(MERL_SHAPE, 0.5))
    assert np.allclose(mono.values, 0.5, rtol=1e-14)
    with pytest.raises(ValueError, match="shape"):
        MerlTable.from_brdf(np.zeros((3, 90, 90, 360)))


def test_wrong_dimensions_and_size_name_the_file(tmp_path: Path) -> None:
    good = write_merl(tmp_path / "good.binary", random_table(2)).read_bytes()
    bad_dims = tmp_path / "dims.binary"
    bad_dims.write_bytes(np.asarray([90, 90, 360], "<i4").tobytes() + good[12:])
    with pytest.raises(MaterialError, match=r"dims\.binary.*dimensions \(90, 90, 360\)"):
        read_merl(bad_dims)
    truncated = tmp_path / "short.binary"
    truncated.write_bytes(good[:-8])
    with pytest.raises(MaterialError, match=r"short\.binary.*truncated"):
        read_merl(truncated)
    tiny = tmp_path / "tiny.binary"
    tiny.write_bytes(b"\x00" * 5)
    with pytest.raises(MaterialError, match="too short"):
        read_merl(tiny)
    with pytest.raises(MaterialError, match="cannot read"):
        read_merl(tmp_path / "absent.binary")


def test_non_finite_samples_are_refused(tmp_path: Path) -> None:
    stored = random_table(3).stored.copy()
    stored[1, 2, 3, 4] = np.nan
    path = write_merl(tmp_path / "nan.binary", MerlTable(stored))
    with pytest.raises(MaterialError, match="NaN"):
        read_merl(path)


def test_write_never_overwrites_unless_asked(tmp_path: Path) -> None:
    path = write_merl(tmp_path / "t.binary", random_table(4))
    before = path.read_bytes()
    with pytest.raises(OutputExistsError):
        write_merl(path, random_table(5))
    assert path.read_bytes() == before
    write_merl(path, random_table(5), overwrite=True)
    assert path.read_bytes() != before


def test_table_checks_its_array() -> None:
    with pytest.raises(ValueError, match="float64"):
        MerlTable(np.zeros((3, *MERL_SHAPE), dtype=np.float32))
