"""Crafted hdf5 dataset files (issue 43, finding 3): each is refused by ``spot run`` with exit 2 and
one ``error:`` line naming the file and the dataset path inside it, before anything is read or
written.

Every file is a tiny Hopper-sized D4RL file (40 rows, 11-D observations, 3-D actions) written with
h5py in the test's own folder under D4RL's real file name, with one array made hostile: an
external link, a soft link that leaves the file or dangles, HDF5 external storage of a file beside
it, a virtual dataset, a 410 GiB declared shape, a compression bomb (under a low limit passed as a
parameter), a filter plugin, a non-numeric or complex dtype, NaN actions, actions a million times
outside the action space and arrays of different lengths.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest

from spot import SpotError, cli
from spot.data import formats, hdf5_checks

N = 40
NAME = "hopper_medium_replay-v2.hdf5"  # D4RL's real file name: resolves to hopper-medium-replay-v2 (Hopper-v5)
GIB = 1 << 30
ROWS_410_GIB = 410 * GIB // (11 * 4)  # rows of Hopper's 11 float32 observations in 410 GiB
HUGE = f"'observations' declares shape ({ROWS_410_GIB}, 11) of float32 (410.0 GiB)"


def _arrays() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {
        "observations": rng.normal(size=(N, 11)).astype(np.float32),
        "actions": rng.uniform(-1, 1, size=(N, 3)).astype(np.float32),
        "rewards": rng.normal(size=N).astype(np.float32),
        "terminals": np.zeros(N, np.float32),
        "timeouts": (np.arange(N) % 20 == 19).astype(np.float32),
    }


def write_d4rl(path: Path, skip: tuple[str, ...] = (), mutate: Callable[[h5py.File, Path], None] | None = None) -> Path:
    """A valid 40-row Hopper D4RL file at ``path`` without the arrays ``skip``, then ``mutate(f, folder)``."""
    with h5py.File(path, "w") as f:
        for key, arr in _arrays().items():
            if key not in skip:
                f.create_dataset(key, data=arr)
        if mutate is not None:
            mutate(f, path.parent)
    return path


# ------------------------------------------------------------------ the hostile arrays
def _other_file(folder: Path) -> Path:
    """A second hdf5 file beside the dataset (what a link or a virtual dataset could pull in)."""
    other = folder / "other.h5"
    with h5py.File(other, "w") as g:
        g["secret"] = np.arange(N, dtype=np.float32)
    return other


def external_link(f, folder):
    f["rewards"] = h5py.ExternalLink(str(_other_file(folder)), "/secret")


def soft_link_outside(f, folder):
    f["zz_elsewhere"] = h5py.ExternalLink(str(_other_file(folder)), "/")  # visited after 'rewards'
    f["rewards"] = h5py.SoftLink("/zz_elsewhere/secret")  # a soft link whose path leaves through it


def soft_link_dangling(f, folder):
    f["rewards"] = h5py.SoftLink("/nowhere/rewards")


def soft_link_loop(f, folder):
    f["rewards"] = h5py.SoftLink("/rewards")


def external_storage(f, folder):
    outside = folder / "outside.bin"  # a file of the test's folder standing in for /etc/passwd
    outside.write_bytes(np.arange(N, dtype=np.float32).tobytes())
    f.create_dataset("rewards", shape=(N,), dtype=np.float32, external=[(str(outside), 0, 4 * N)])


def virtual_dataset(f, folder):
    layout = h5py.VirtualLayout(shape=(N,), dtype=np.float32)
    layout[:] = h5py.VirtualSource(str(_other_file(folder)), "secret", shape=(N,))
    f.create_virtual_dataset("rewards", layout)


def declared_410_gib(f, folder):
    rows = ROWS_410_GIB  # float32 rows of Hopper's 11 observations: 410 GiB, none of it written
    f.create_dataset("observations", shape=(rows, 11), dtype=np.float32, chunks=(1024, 11))


def gzip_bomb(f, folder):
    # 4 MiB of zeros in gzip chunks: a few KiB in the file (the test lowers the cap to 10x)
    f.create_dataset("rewards", data=np.zeros(1 << 20, np.float32), chunks=(1 << 18,), compression="gzip")


def filter_plugin(f, folder):
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_chunk((10,))
    dcpl.set_filter(307, h5py.h5z.FLAG_OPTIONAL, ())  # bzip2's id: HDF5 would look for a plugin to run
    dsid = h5py.h5d.create(f.id, b"rewards", h5py.h5t.NATIVE_FLOAT, h5py.h5s.create_simple((N,)), dcpl=dcpl)
    h5py.Dataset(dsid)[:] = np.zeros(N, np.float32)


def string_actions(f, folder):
    f["actions"] = np.array([b"abc"] * N * 3, dtype="S3").reshape(N, 3)


def complex_actions(f, folder):
    f["actions"] = (np.ones((N, 3)) + 1j).astype(np.complex64)


def nan_actions(f, folder):
    actions = _arrays()["actions"]
    actions[7, 1] = np.nan
    f["actions"] = actions


def actions_far_outside(f, folder):
    f["actions"] = _arrays()["actions"] * 1e6  # Hopper's actions lie in [-1, 1]


def inconsistent_lengths(f, folder):
    f["rewards"] = np.zeros(N - 5, np.float32)


# (id, arrays the writer leaves out, mutate, what the error line must contain besides the file name)
CASES = [
    ("external-link", ("rewards",), external_link, "'rewards' is an external link to"),
    (
        "soft-link-outside",
        ("rewards",),
        soft_link_outside,
        "soft link 'rewards' points to '/zz_elsewhere/secret', which passes through an external link",
    ),
    ("soft-link-dangling", ("rewards",), soft_link_dangling, "soft link 'rewards' points to '/nowhere/rewards'"),
    ("soft-link-loop", ("rewards",), soft_link_loop, "soft link 'rewards' is a chain of more than 16 soft links"),
    ("external-storage", ("rewards",), external_storage, "'rewards' stores its data in the external file"),
    ("virtual-dataset", ("rewards",), virtual_dataset, "'rewards' is a virtual dataset (VDS)"),
    ("declared-410-GiB", ("observations",), declared_410_gib, HUGE),
    ("gzip-bomb", ("rewards",), gzip_bomb, "'rewards' declares shape (1048576,) of float32 (4.0 MiB) but stores"),
    ("filter-plugin", ("rewards",), filter_plugin, "'rewards' is compressed with HDF5 filter 307"),
    ("string-dtype", ("actions",), string_actions, "'actions' has dtype |S3; expected numbers"),
    ("complex-dtype", ("actions",), complex_actions, "'actions' has dtype complex64; expected numbers"),
    ("nan-actions", ("actions",), nan_actions, "'actions' contains NaN or inf (first at index (7, 1))"),
    ("actions-1e6-outside", ("actions",), actions_far_outside, "'actions' has the value"),
    ("inconsistent-lengths", ("rewards",), inconsistent_lengths, "'rewards' has 35 rows but 'observations' has 40"),
]
BOMB_LIMITS = formats.ReadLimits(max_expansion=10.0, expansion_floor=1 << 20)  # tiny test, same check


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("skip, mutate, fragment", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_a_crafted_hdf5_file_is_one_clear_error_and_writes_nothing(
    tmp_path, monkeypatch, capsys, skip, mutate, fragment
):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.setenv("SPOT_CACHE_DIR", str(tmp_path / "stage-cache"))
    monkeypatch.setenv("SPOT_DATA_DIR", str(tmp_path / "data"))
    if mutate is gzip_bomb:
        monkeypatch.setattr(hdf5_checks, "DEFAULT_LIMITS", BOMB_LIMITS)
    path = write_d4rl(tmp_path / NAME, skip, mutate)
    before = _tree(tmp_path)
    rc = cli.main(
        ["run", "method=oracle", "budget=tiny", f"data.name={path}", f"tracking.uri=sqlite:///{tmp_path}/m.db"]
    )
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert rc == 2, err
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert f"dataset file '{path}" in lines[0] and fragment in lines[0], lines[0]
    assert _tree(tmp_path) == before  # no store, no cache, no run; the inputs unchanged


def test_actions_outside_name_the_row_column_and_bounds(tmp_path, monkeypatch, capsys):
    """The action-space error names the file's row and column, the value and Hopper's bounds."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    actions = _arrays()["actions"]
    actions[13, 2] = 1.2  # 10 % of [-1, 1]'s width beyond its bound: outside the 5 % slack

    def one_outside(f, folder):
        f["actions"] = actions

    path = write_d4rl(tmp_path / NAME, ("actions",), one_outside)
    assert cli.main(["run", "method=oracle", "budget=tiny", f"data.name={path}"]) == 2
    line = capsys.readouterr().err.strip()
    assert "'actions' has the value 1.2 in column 2 at row 13 (1 values outside)" in line, line
    assert "expected the action space of Hopper-v5, [-1, 1] (up to 5% of its width beyond)" in line, line


def test_the_reader_refuses_before_reading(tmp_path):
    """The reader itself, without the CLI: the same refusals, and the memory budget as a parameter."""
    path = write_d4rl(tmp_path / NAME, ("rewards",), external_storage)
    with pytest.raises(SpotError, match="stores its data in the external file"):
        formats.load_dataset_file(path)
    with pytest.raises(SpotError, match="stores its data in the external file"):
        formats.detect_format(path)
    plain = write_d4rl(tmp_path / "plain.hdf5")
    declared = sum(a.nbytes for a in _arrays().values())
    assert declared == 2720  # 40 rows of 11 + 3 + 1 + 1 + 1 float32 values: 2.7 KiB, twice that 5.3 KiB
    with pytest.raises(SpotError, match=r"needs 5.3 KiB \(twice their 2.7 KiB\) but 100 bytes of memory"):
        formats.read_d4rl_hdf5(plain, formats.ReadLimits(memory_bytes=100))
    raw = formats.read_d4rl_hdf5(plain, formats.ReadLimits(memory_bytes=2 * declared))
    assert len(raw) == N
    bomb = write_d4rl(tmp_path / "bomb.hdf5", ("rewards",), gzip_bomb)
    with pytest.raises(SpotError, match="expected at most 10 times its stored size"):
        formats.read_d4rl_hdf5(bomb, BOMB_LIMITS)
    with pytest.raises(SpotError, match="'rewards' has 1048576 rows but 'observations' has 40"):
        formats.read_d4rl_hdf5(bomb)  # the default cap lets 4 MiB through; the row check then refuses it


def test_links_inside_the_file_are_read(tmp_path):
    """Soft links and extra hard links to arrays of the same file are fine: the file reads as if
    the arrays were at the top level."""

    def linked(f, folder):
        for key, arr in _arrays().items():
            f[f"store/{key}"] = arr
            f[key] = h5py.SoftLink(f"/store/{key}")
        f["store/again"] = f["store/rewards"]  # a second hard link to one array

    raw = formats.read_d4rl_hdf5(write_d4rl(tmp_path / NAME, tuple(_arrays()), linked))
    np.testing.assert_array_equal(raw.rewards, _arrays()["rewards"])
    np.testing.assert_array_equal(raw.actions, _arrays()["actions"])


def test_a_file_with_too_many_links_is_refused(tmp_path):
    def many(f, folder):
        for i in range(30):
            f.create_group(f"g{i}")

    path = write_d4rl(tmp_path / NAME, (), many)
    with pytest.raises(SpotError, match="holds more than 20 links"):
        formats.read_d4rl_hdf5(path, formats.ReadLimits(max_links=20))
    assert len(formats.read_d4rl_hdf5(path)) == N


def test_a_locally_written_gzip_file_passes_the_default_cap(tmp_path):
    """spot's own files (gzip level 1) with long all-zero flag arrays: gzip's ratio stays under the cap."""
    n = 200_000
    raw = formats.RawDataset(
        observations=np.zeros((n, 11), np.float32),
        actions=np.zeros((n, 3), np.float32),
        rewards=np.zeros(n, np.float32),
        terminals=np.zeros(n, bool),
        timeouts=np.zeros(n, bool),
    )
    path = tmp_path / NAME
    formats.write_d4rl_hdf5(raw, path)
    with h5py.File(path) as f:
        ratio = f["observations"].size * 4 / f["observations"].id.get_storage_size()
    assert ratio > 100  # zeros do compress: the cap is what lets them through
    limits = formats.ReadLimits(expansion_floor=0)  # every array ratio-checked
    assert len(formats.read_d4rl_hdf5(path, limits)) == n
