"""The quickstart's dataset shipped inside the package (spot/data/embedded/): copied in, verified,
used only when it is what the installed recipe and packages build, and byte-equal to a build here."""

import hashlib
import json
import os
import shutil
import tomllib
from fnmatch import fnmatch
from pathlib import Path

import numpy as np
import pytest

from spot import SpotError
from spot.data import embedded, formats, registry
from spot.data.dataset import RawDataset
from spot.recipes import locomotion

ROOT = Path(__file__).resolve().parents[1]
NAME, SIZE, SEED = "hopper-medium-replay", "small", 0
SHIPPED = ROOT / "spot" / "data" / "embedded" / f"{NAME}__{SIZE}__seed{SEED}.hdf5"
SHIPPED_CARD = SHIPPED.with_suffix(".card.json")


@pytest.fixture
def data_dir(tmp_path, monkeypatch):
    """A fresh SPOT_DATA_DIR, no shared store."""
    monkeypatch.setenv("SPOT_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.delenv("SPOT_STORE", raising=False)
    return tmp_path / "data"


@pytest.fixture
def recipe_calls(monkeypatch):
    """The locomotion recipe replaced by a cheap fake that records its calls (a few rows of a
    made-up dataset, the card fields a recipe writes, a build time that differs call by call)."""
    calls = []

    def fake_build(name, size, seed, cache_dir, progress=True):
        calls.append((name, size, seed))
        n = 6
        obs = np.arange(n * 11, dtype=np.float32).reshape(n, 11)
        raw = RawDataset(
            observations=obs,
            actions=np.zeros((n, 3), np.float32),
            rewards=np.ones(n, np.float32),
            terminals=np.eye(n, dtype=bool)[-1],
            timeouts=np.zeros(n, bool),
            next_observations=obs + 1,
            name=f"{name}-{size}",
        )
        card = {"recipe": locomotion.RECIPE, "transitions": n, "build_time_s": 0.5 + len(calls)}
        card["sac"] = {"steps": 10, "train_time_s": 0.25 * len(calls), "peak_rss_mb": 100.0 + len(calls)}
        return raw, card

    monkeypatch.setattr(locomotion, "build", fake_build)
    return calls


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _shipped_copy(tmp_path: Path, monkeypatch, edit_card=None, edit_bytes=None) -> Path:
    """The shipped files copied to a tmp folder (optionally edited) that the registry then uses."""
    folder = tmp_path / "shipped"
    folder.mkdir()
    hdf5 = folder / SHIPPED.name
    shutil.copyfile(SHIPPED, hdf5)
    card = json.loads(SHIPPED_CARD.read_text())
    if edit_card:
        edit_card(card)
    hdf5.with_suffix(".card.json").write_text(json.dumps(card))
    if edit_bytes:
        data = bytearray(hdf5.read_bytes())
        edit_bytes(data)
        hdf5.write_bytes(bytes(data))
    monkeypatch.setattr(embedded, "FOLDER", folder)
    return hdf5


def _written(folder: Path) -> list[str]:
    """What a build left in the data dir, lock files and the recipe's work folder aside."""
    if not folder.exists():
        return []
    return sorted(p.name for p in folder.iterdir() if p.suffix != ".lock" and p.name != "_work")


# --------------------------------------------------------------------------- the shipped files
def test_the_shipped_card_describes_the_shipped_file():
    card = json.loads(SHIPPED_CARD.read_text())
    assert card["sha256"] == _sha(SHIPPED) and card["bytes"] == SHIPPED.stat().st_size
    assert SHIPPED.stat().st_size <= 2 * 1024 * 1024
    assert (card["name"], card["size"], card["seed"], card["source"]) == (NAME, SIZE, SEED, "recipe")
    assert card["recipe"] == locomotion.RECIPE
    assert card["recipe_version"] == locomotion.recipe_version(NAME, SIZE)
    assert set(embedded.PACKAGES) <= set(card["versions"])
    assert {"machine", "cpu", "cpu_features"} <= set(card["host"])
    raw = formats.read_d4rl_hdf5(SHIPPED)  # it reads as a dataset, and holds the card's data fields
    assert len(raw) == card["transitions"]
    outside = {k: v for k, v in card.items() if k not in ("sha256", "bytes")}  # of the file, not in it
    assert raw.metadata["spot_card"] == embedded.data_card(outside)


def test_the_package_data_ships_the_files():
    globs = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["spot"]
    for path in (SHIPPED, SHIPPED_CARD):
        rel = path.relative_to(ROOT / "spot").as_posix()
        assert any(fnmatch(rel, g) for g in globs), rel


# --------------------------------------------------------------------------- using the copy
def test_a_fresh_data_dir_gets_the_shipped_copy_without_running_the_recipe(data_dir, recipe_calls, capsys):
    path = registry.build(NAME, SIZE, SEED)
    assert recipe_calls == []  # no SAC ran
    assert path.read_bytes() == SHIPPED.read_bytes()
    card = registry.read_card(path)
    assert card["obtained"] == "embedded" and card["source"] == "recipe"
    assert card["sha256"] == _sha(path)
    shipped = json.loads(SHIPPED_CARD.read_text())
    assert shipped["obtained"] == "built"  # where the shipped file was made
    assert {k: v for k, v in card.items() if k != "obtained"} == {k: v for k, v in shipped.items() if k != "obtained"}
    assert "embedded copy" in capsys.readouterr().err
    assert _written(data_dir) == sorted([path.name, registry.card_path(path).name])
    assert registry.build(NAME, SIZE, SEED) == path and recipe_calls == []  # then reused
    ds, loaded = registry.load(NAME, SIZE, SEED)
    assert loaded["obtained"] == "embedded" and len(ds) > 0


def test_a_tampered_shipped_file_is_refused_and_nothing_is_written(data_dir, recipe_calls, tmp_path, monkeypatch):
    def flip(data):
        data[len(data) // 2] ^= 0xFF

    hdf5 = _shipped_copy(tmp_path, monkeypatch, edit_bytes=flip)
    with pytest.raises(SpotError, match=f"embedded dataset '{hdf5}' has sha256 .*its card records"):
        registry.build(NAME, SIZE, SEED)
    assert recipe_calls == [] and _written(data_dir) == []


def test_a_shipped_file_of_another_size_than_its_card_is_refused(data_dir, recipe_calls, tmp_path, monkeypatch):
    hdf5 = _shipped_copy(tmp_path, monkeypatch, edit_bytes=lambda data: data.extend(b"\0" * 8))
    with pytest.raises(SpotError, match=f"embedded dataset '{hdf5}' has {SHIPPED.stat().st_size + 8} bytes"):
        registry.build(NAME, SIZE, SEED)
    assert recipe_calls == [] and _written(data_dir) == []


def test_a_shipped_card_that_is_not_json_is_refused(data_dir, recipe_calls, tmp_path, monkeypatch):
    hdf5 = _shipped_copy(tmp_path, monkeypatch)
    hdf5.with_suffix(".card.json").write_text("{not json")
    with pytest.raises(SpotError, match="embedded dataset card .* does not read as JSON"):
        registry.build(NAME, SIZE, SEED)
    assert recipe_calls == [] and _written(data_dir) == []


@pytest.mark.parametrize(
    ("edit", "why"),
    [
        (lambda c: c["versions"].update(mujoco="0.0.1"), "built with mujoco 0.0.1"),
        (lambda c: c["versions"].update(jax="0.0.2"), "built with jax 0.0.2"),
        (lambda c: c.update(recipe_version=-1), "recipe version -1"),
        (lambda c: c.update(recipe="another-recipe"), "recipe 'another-recipe'"),
    ],
)
def test_a_mismatching_shipped_build_is_not_used_and_the_recipe_builds(
    edit, why, data_dir, recipe_calls, tmp_path, monkeypatch, capsys
):
    _shipped_copy(tmp_path, monkeypatch, edit_card=edit)
    path = registry.build(NAME, SIZE, SEED)
    assert recipe_calls == [(NAME, SIZE, SEED)]
    err = capsys.readouterr().err
    assert "from its recipe, not the embedded copy" in err and why in err
    card = registry.read_card(path)
    assert card["obtained"] == "built" and card["host"] == embedded.host_facts()
    assert card["xla_flags"] == os.environ.get("XLA_FLAGS", "")


def test_from_recipe_builds_even_where_a_copy_is_shipped_or_was_copied(data_dir, recipe_calls):
    path = registry.build(NAME, SIZE, SEED)  # the copy
    assert registry.read_card(path)["obtained"] == "embedded" and recipe_calls == []
    registry.build(NAME, SIZE, SEED, from_recipe=True)  # replaces the copy with a build
    assert recipe_calls == [(NAME, SIZE, SEED)] and registry.read_card(path)["obtained"] == "built"
    registry.build(NAME, SIZE, SEED, from_recipe=True)  # a build here is reused
    registry.build(NAME, SIZE, SEED)
    assert len(recipe_calls) == 1
    registry.build(NAME, SIZE, SEED, force=True)  # force: the recipe again, never the copy
    assert len(recipe_calls) == 2 and registry.read_card(path)["obtained"] == "built"


def test_equal_data_give_equal_bytes_whatever_the_build_facts(data_dir, recipe_calls):
    first = registry.build(NAME, SIZE, SEED, from_recipe=True)
    one, card_one = first.read_bytes(), registry.read_card(first)
    registry.build(NAME, SIZE, SEED, force=True)
    card_two = registry.read_card(first)
    assert card_one["build_time_s"] != card_two["build_time_s"]  # the fake's times differ per build
    assert card_one["sac"]["train_time_s"] != card_two["sac"]["train_time_s"]
    assert first.read_bytes() == one and card_two["sha256"] == card_one["sha256"] == _sha(first)
    inner = formats.read_d4rl_hdf5(first).metadata["spot_card"]  # the file holds no build facts
    assert "build_time_s" not in inner and "train_time_s" not in inner["sac"]
    assert not {"host", "xla_flags", "obtained"} & set(inner)
    assert inner["sac"] == {"steps": 10} and inner["transitions"] == 6 and inner["source"] == "recipe"


def test_host_facts_name_the_cpu_and_hash_its_features():
    facts = embedded.host_facts()
    assert set(facts) == {"machine", "cpu", "cpu_features"} and facts["cpu"]
    assert len(facts["cpu_features"]) == 12 and int(facts["cpu_features"], 16) >= 0
    features = embedded.cpu_features()
    assert features == sorted(features)
    assert hashlib.sha256(" ".join(features).encode()).hexdigest()[:12] == facts["cpu_features"]


def test_the_cli_copies_and_info_says_so(data_dir, recipe_calls, capsys):
    from spot.cli import main

    assert main(["data", "build", NAME, "--size", SIZE, "--quiet"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"copied {registry.dataset_path(NAME, SIZE, SEED)}") and recipe_calls == []
    assert main(["data", "info", NAME, "--size", SIZE]) == 0
    info = json.loads(capsys.readouterr().out)
    assert "embedded copy" in info["source"] and info["card"]["obtained"] == "embedded"
    assert info["summary"]["transitions"] == len(registry.load(NAME, SIZE, SEED)[0])
    assert main(["data", "build", NAME, "--size", SIZE, "--from-recipe", "--quiet"]) == 0
    assert capsys.readouterr().out.startswith("built ") and recipe_calls == [(NAME, SIZE, SEED)]
    assert main(["data", "info", NAME, "--size", SIZE]) == 0
    assert json.loads(capsys.readouterr().out)["source"] == "recipe: built on this machine"


# --------------------------------------------------------------------------- a build here, compared
@pytest.mark.slow
def test_a_recipe_build_here_is_byte_equal_to_the_shipped_file(data_dir, capsys):
    """SAC on Hopper, 80k steps, in a fresh data dir (minutes): the same bytes as the shipped
    file, and so the same data digest, where this host's CPU is the one that built it. XLA compiles
    for the host's CPU features, so on another CPU the bytes may differ (docs/datasets.md, "The
    embedded quickstart dataset"); there the test skips, naming both hosts."""
    shipped = json.loads(SHIPPED_CARD.read_text())
    here = embedded.host_facts()
    if shipped["host"] != here:
        pytest.skip(f"the shipped file was built on {shipped['host']}; this host is {here}")
    path = registry.build(NAME, SIZE, SEED, from_recipe=True, progress=False)
    card = registry.read_card(path)
    assert card["obtained"] == "built" and card["sac_cache_hit"] is False  # SAC ran here
    assert _sha(path) == card["sha256"] == shipped["sha256"]
    built = formats.read_d4rl_hdf5(path).qlearning().fingerprint()
    assert built == formats.read_d4rl_hdf5(SHIPPED).qlearning().fingerprint()  # runs tag the same data_digest
